"""A smooth free-form object as a laser scanner sees it: no edges, no clutter (the pairs that
start with FPFH: byoc_cli.pipeline.feature_choice)."""

from __future__ import annotations

import numpy as np


def smooth_scan(seed: int, n: int = 40000) -> np.ndarray:
    """``(n, 3)`` points on the half facing +z of a smooth ellipsoid 20 cm long, gently
    deformed; another ``seed`` samples the same surface at other points."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((4 * n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] > 0.1][:n]
    r = 1 + 0.15 * u[:, 0] * u[:, 1] + 0.1 * u[:, 2] ** 2
    return u * r[:, None] * np.array([0.1, 0.07, 0.05])
