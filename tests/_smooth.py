"""A smooth free-form object as a laser scanner sees it: no edges, no clutter (the pairs that
start with FPFH: byoc_cli.pipeline.feature_choice)."""

from __future__ import annotations

import numpy as np


def smooth_scan(seed: int, n: int = 40000, even: bool = False) -> np.ndarray:
    """``(n, 3)`` points on the half facing +z of a smooth ellipsoid 20 cm long, gently
    deformed; another ``seed`` samples the same surface at other points. ``even``: sampled
    at a near constant step, as a scanner's rays sample it (a golden-angle spiral turned by
    the seed), instead of at random."""
    rng = np.random.default_rng(seed)
    if even:
        i = np.arange(4 * n) + 0.5
        polar, azimuth = np.arccos(1 - 2 * i / (4 * n)), np.pi * (1 + 5**0.5) * i
        u = np.stack([np.cos(azimuth), np.sin(azimuth), 0 * i], 1) * np.sin(polar)[:, None]
        u[:, 2] = np.cos(polar)
        u = u @ np.linalg.qr(rng.standard_normal((3, 3)))[0].T
    else:
        u = rng.standard_normal((4 * n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] > 0.1][:n]
    r = 1 + 0.15 * u[:, 0] * u[:, 1] + 0.1 * u[:, 2] ** 2
    return u * r[:, None] * np.array([0.1, 0.07, 0.05])
