"""Rigid transforms and ray casting of benchmarks/scan_sim.py: 4x4 transforms (``x_tgt = R x_src
+ t``), an Open3D raycasting scene of a mesh and a scanner's returns from it.
"""

from __future__ import annotations

import numpy as np

Pair = tuple[np.ndarray, np.ndarray, np.ndarray]  # src (N, 3), tgt (M, 3), T_gt (4, 4)


def quiet_open3d():
    """open3d, its log set to errors only."""
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def rigid(R: np.ndarray, t) -> np.ndarray:
    """The 4x4 transform of rotation ``R (3, 3)`` and translation ``t (3,)``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def rotation_xyz(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """``(3, 3)`` rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (degrees)."""
    r, p, y = np.radians([roll_deg, pitch_deg, yaw_deg])
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def translation(offset) -> np.ndarray:
    """The 4x4 translation by ``offset (3,)``."""
    return rigid(np.eye(3), np.asarray(offset, dtype=np.float64))


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points (N, 3)`` mapped by ``T (4, 4)``: ``points @ R.T + t``, float64 ``(N, 3)``."""
    points = np.asarray(points, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]


def relative(T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
    """``T_b_a (4, 4)``: maps frame ``a`` into frame ``b`` given both poses in the world."""
    return np.linalg.solve(T_world_b, T_world_a)


def raycasting_scene(mesh):
    """An ``open3d.t.geometry.RaycastingScene`` of a legacy ``TriangleMesh``."""
    o3d = quiet_open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def cast(scene, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distances ``(N,)`` float64 along unit ``directions (N, 3)`` from ``origin (3,)`` to the
    first hit of ``scene`` (``inf`` where a ray hits nothing)."""
    o3d = quiet_open3d()
    rays = np.empty((len(directions), 6), dtype=np.float32)
    rays[:, :3] = origin
    rays[:, 3:] = directions
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    return hits["t_hit"].numpy().astype(np.float64)


def cast_full(scene, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cast` and the unit normals ``(N, 3)`` of the triangles hit (zeros for a miss)."""
    o3d = quiet_open3d()
    rays = np.empty((len(directions), 6), dtype=np.float32)
    rays[:, :3] = origin
    rays[:, 3:] = directions
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    normals = hits["primitive_normals"].numpy().astype(np.float64)
    return hits["t_hit"].numpy().astype(np.float64), normals


def scan(
    scene,
    T_world_sensor: np.ndarray,
    directions: np.ndarray,
    rng: np.random.Generator,
    noise: float,
    max_range: float,
    min_range: float = 0.0,
) -> np.ndarray:
    """Ray-cast a scanner: ``directions (K, 3)`` unit rays in the sensor frame, from the sensor
    at ``T_world_sensor (4, 4)``; each return's range gets gaussian noise of std ``noise``.

    Returns ``(N, 3)`` float64 points in the sensor frame (N <= K: returns within
    ``[min_range, max_range]``), in the order of ``directions``.
    """
    world = directions @ T_world_sensor[:3, :3].T
    t = cast(scene, T_world_sensor[:3, 3], world)
    keep = np.isfinite(t) & (t <= max_range) & (t >= min_range)
    ranges = t[keep] + noise * rng.standard_normal(int(keep.sum()))
    return directions[keep] * ranges[:, None]
