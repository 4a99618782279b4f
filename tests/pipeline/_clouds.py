"""Small synthetic clouds for the engine's tests: a box's surface and a known motion of it."""

from __future__ import annotations

import numpy as np


def cube(seed: int = 0) -> np.ndarray:
    """``(4000, 3)`` points on the faces of a 3 x 2 x 1.6 box."""
    rng = np.random.default_rng(seed)
    n = 4000
    pts = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = np.sign(pts[np.arange(n), axis])
    return pts * np.array([1.5, 1.0, 0.8])


def moved(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``pts (N, 3)`` under a known ``T (4, 4)`` (0.2 rad about z and a shift), and ``T``."""
    c, s = np.cos(0.2), np.sin(0.2)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [0.2, -0.1, 0.05]
    return pts @ T[:3, :3].T + T[:3, 3], T
