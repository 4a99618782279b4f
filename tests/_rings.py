"""Small scenes scanned exactly in the sensor frame. One (a ground plane and a box) scanned
two ways: by a spinning LiDAR (rings of returns, dense along each ring, sparse across) and by
a depth camera (a pixel grid: even sampling). The same surfaces, two samplings: what tells a
scan sampled along lines from one sampled evenly. And a room scanned from inside by a
terrestrial laser scanner (:func:`room_scan`), and a wall facing a sensor (:func:`wall`).

The sensor is at ``(0, 0, HEIGHT)`` above the ground ``z = 0``; the box ``BOX`` stands on the
ground in front of it (+x). Ranges are exact (ray casting by the slab method).
"""

from __future__ import annotations

import numpy as np

HEIGHT = 1.8
#: (min corner, max corner) in metres
BOX = (np.array([5.0, -3.0, 0.0]), np.array([8.0, 3.0, 3.0]))
#: returns beyond this range are dropped
MAX_RANGE = 30.0


def _cast(directions: np.ndarray) -> np.ndarray:
    """``(K, 3)`` points where unit ``directions (N, 3)`` from the sensor first meet the ground
    or the box within :data:`MAX_RANGE` (rays that meet neither are dropped)."""
    origin = np.array([0.0, 0.0, HEIGHT])
    with np.errstate(divide="ignore", invalid="ignore"):
        ground = np.where(directions[:, 2] < 0, -HEIGHT / directions[:, 2], np.inf)
        inv = 1.0 / directions
        t0 = (BOX[0] - origin) * inv
        t1 = (BOX[1] - origin) * inv
    near = np.nan_to_num(np.minimum(t0, t1), nan=-np.inf).max(axis=1)
    far = np.nan_to_num(np.maximum(t0, t1), nan=np.inf).min(axis=1)
    box = np.where((near <= far) & (near > 0), near, np.inf)
    t = np.minimum(ground, box)
    hit = t < MAX_RANGE
    return origin + directions[hit] * t[hit, None]


def ring_scan(rings: int = 16, steps: int = 900, lowest: float = -25.0, highest: float = 5.0):
    """``(N, 3)`` a spinning LiDAR's returns: ``rings`` elevations from ``lowest`` to
    ``highest`` degrees, ``steps`` azimuths each."""
    elevation = np.radians(np.linspace(lowest, highest, rings))
    azimuth = np.linspace(0.0, 2.0 * np.pi, steps, endpoint=False)
    E, A = np.meshgrid(elevation, azimuth, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    return _cast(d)


def camera_scan(width: int = 160, height: int = 120, focal: float = 100.0):
    """``(N, 3)`` a depth camera's returns looking along +x, slightly down, at the box: one
    ray per pixel of a ``width x height`` grid (even sampling)."""
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, np.arange(height) + 0.5 - height / 2)
    d = np.stack([np.full(u.size, focal), -u.ravel(), -v.ravel() - 0.3 * focal], axis=1)
    return _cast(d / np.linalg.norm(d, axis=1, keepdims=True))


#: (min corner, max corner) of the room of :func:`room_scan`, around its scanner at the origin
ROOM = (np.array([-2.0, -3.0, -1.5]), np.array([5.0, 2.0, 1.3]))


def room_scan(step_deg: float = 1.0) -> np.ndarray:
    """``(N, 3)`` a terrestrial laser scanner's returns from the inside of the empty box
    :data:`ROOM`, at the origin: one ray per ``step_deg`` of azimuth and elevation (-80 to
    +80 deg), so that the points crowd near the scanner as a laser scan's do."""
    elevation = np.radians(np.arange(-80.0, 80.0 + step_deg / 2, step_deg))
    azimuth = np.radians(np.arange(0.0, 360.0, step_deg))
    E, A = np.meshgrid(elevation, azimuth, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, ROOM[1] / d, np.where(d < 0, ROOM[0] / d, np.inf)).min(axis=1)
    return d * t[:, None]


def wall(z: float = 3.0, half: float = 1.0, step: float = 0.02) -> np.ndarray:
    """``(N, 3)`` a square wall of side ``2 half`` facing a sensor at the origin, at distance
    ``z`` along +z, sampled on a grid of ``step``."""
    ticks = np.arange(-half, half + step / 2, step)
    x, y = np.meshgrid(ticks, ticks, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
