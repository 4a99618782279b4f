"""The simulated laser scans of an object of benchmarks/scan_sim.py: a triangle mesh fused (TSDF)
from a real RGB-D sequence that circles an object on a table, the table cut off, scaled, and
ray-cast by a dense pinhole laser scanner from two viewpoints on the arc the camera covered.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from _scan_sim_geometry import apply, quiet_open3d, raycasting_scene, relative, rigid, scan

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
OBJECT_SEQUENCE = "rgbd/realsense_tabletop"
OBJECT_VOXEL_FRACTION = 1 / 50  # of the object's size, the hand-set voxel for objects


def _sequence_frames(sequence: Path) -> list[tuple[Path, np.ndarray]]:
    """``(depth PNG, T_world_cam (4, 4))`` of each frame of a 3DMatch RGB-D sequence."""
    frames = []
    for depth in sorted(sequence.glob("seq-*/frame-*.depth.png")):
        pose = np.loadtxt(str(depth).replace(".depth.png", ".pose.txt"))
        frames.append((depth, pose.reshape(4, 4)))
    if not frames:
        raise FileNotFoundError(f"{sequence}: no seq-*/frame-*.depth.png (3DMatch RGB-D layout)")
    return frames


def _canonical(o3d, vertices: np.ndarray, triangles: np.ndarray):
    """A legacy mesh of ``vertices (V, 3)`` and ``triangles (F, 3)`` with both sorted (the
    TSDF's hash map returns them in an order that changes from run to run)."""
    order = np.lexsort(vertices.T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    tris = rank[triangles]
    tris = tris[np.lexsort(tris.T[::-1])]
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices[order]), o3d.utility.Vector3iVector(tris)
    )


def fused_mesh(sequence: Path, voxel: float = 0.002, cache: Path | None = None):
    """The TSDF mesh of a 3DMatch-layout RGB-D sequence (depth in mm, ``pose.txt``
    camera-to-world, ``camera-intrinsics.txt``), fused with Open3D's ``VoxelBlockGrid`` at
    ``voxel`` m (truncation 4 voxels, depth up to 1.2 m, voxels seen at least 3 times), in the
    sequence's world frame; read from / written to ``cache`` (a folder) when given."""
    o3d = quiet_open3d()
    name = f"{Path(sequence).name}-tsdf-{voxel * 1000:g}mm.ply"
    if cache is not None and (Path(cache) / name).exists():
        return o3d.io.read_triangle_mesh(str(Path(cache) / name))
    o3c = o3d.core
    K = o3c.Tensor(np.loadtxt(Path(sequence) / "camera-intrinsics.txt"), o3c.float64)
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"),
        attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1), (1)),
        voxel_size=voxel,
        block_resolution=16,
        block_count=20000,
    )
    for depth_path, pose in _sequence_frames(Path(sequence)):
        depth = o3d.t.io.read_image(str(depth_path))
        extrinsic = o3c.Tensor(np.linalg.inv(pose), o3c.float64)
        args = (depth, K, extrinsic, 1000.0, 1.2)
        blocks = grid.compute_unique_block_coordinates(*args, trunc_voxel_multiplier=4.0)
        grid.integrate(blocks, *args, trunc_voxel_multiplier=4.0)
    fused = grid.extract_triangle_mesh(weight_threshold=3.0).to_legacy()
    mesh = _canonical(o3d, np.asarray(fused.vertices), np.asarray(fused.triangles))
    if cache is not None:
        Path(cache).mkdir(parents=True, exist_ok=True)
        o3d.io.write_triangle_mesh(str(Path(cache) / name), mesh)
    return mesh


def _table_plane(
    points: np.ndarray, up: np.ndarray, rng: np.random.Generator, tol: float = 0.004
) -> tuple[np.ndarray, float]:
    """``(n (3,), d)`` of the plane ``n.x + d = 0`` with the most of ``points (N, 3)`` within
    ``tol`` among planes within 30 deg of ``up (3,)`` (seeded RANSAC, then least squares on
    its inliers); ``n`` points along ``up``."""
    best, best_count = None, -1
    for _ in range(500):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-9:
            continue
        n /= np.linalg.norm(n)
        if abs(n @ up) < np.cos(np.radians(30)):
            continue
        count = int(np.sum(np.abs((points - a) @ n) < tol))
        if count > best_count:
            best, best_count = (n, -n @ a), count
    n, d = best
    inliers = points[np.abs(points @ n + d) < tol]
    centroid = inliers.mean(axis=0)
    centred = inliers - centroid
    n = np.linalg.eigh(centred.T @ centred)[1][:, 0]  # the least spread direction
    n = n if n @ up > 0 else -n
    return n, float(-n @ centroid)


class ObjectModel(NamedTuple):
    """An object mesh in its own frame and the arc the real camera covered around it."""

    mesh: object  # legacy open3d TriangleMesh: table plane at z = 0, z up, metres
    center: np.ndarray  # (3,) the centre of its bounding box
    radius: float  # half the bounding box's diagonal
    azimuth_deg: tuple[float, float]  # the real camera's azimuths, first and last frame
    elevation_deg: float  # the real camera's median elevation above the table
    distance: float  # the real camera's median distance from the object, scaled


def object_model(
    sequence: Path | None = None, size: float = 0.2, cache: Path | None = None
) -> ObjectModel:
    """The object of an RGB-D sequence that circles an object on a table: the fused mesh
    (:func:`fused_mesh`) within 35 cm of the point the cameras' optical axes pass closest to,
    above the table plane (more than 4 mm), its largest connected part, in a frame on the
    table (z up) and scaled so that its bounding box's longest side is ``size`` m."""
    o3d = quiet_open3d()
    sequence = Path(sequence) if sequence is not None else DATA / OBJECT_SEQUENCE
    poses = np.array([pose for _, pose in _sequence_frames(sequence)])
    origins, axes = poses[:, :3, 3], poses[:, :3, 2]
    projectors = np.eye(3) - axes[:, :, None] * axes[:, None, :]
    focus = np.linalg.solve(projectors.sum(0), np.einsum("kij,kj->i", projectors, origins))
    up = -poses[:, :3, 1].mean(axis=0)  # image rows point down
    up /= np.linalg.norm(up)
    mesh = fused_mesh(sequence, cache=cache)
    vertices = np.asarray(mesh.vertices)
    near = vertices[np.linalg.norm(vertices - focus, axis=1) < 0.4]
    n, d = _table_plane(near, up, np.random.default_rng(0))
    x = np.cross(n, poses[0, :3, 2])
    x /= np.linalg.norm(x)
    on_table = focus - (focus @ n + d) * n
    T_obj_world = np.linalg.inv(rigid(np.stack([x, np.cross(n, x), n], axis=1), on_table))
    local = apply(T_obj_world, vertices)
    keep = (local[:, 2] > 0.004) & (np.linalg.norm(local[:, :2], axis=1) < 0.35)
    part = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(local), o3d.utility.Vector3iVector(np.asarray(mesh.triangles))
    )
    part.remove_vertices_by_mask(~keep)
    clusters, counts, _ = part.cluster_connected_triangles()
    part.remove_triangles_by_mask(np.asarray(clusters) != int(np.argmax(np.asarray(counts))))
    part.remove_unreferenced_vertices()
    lo, hi = part.get_min_bound(), part.get_max_bound()
    scale = size / float(np.max(hi - lo))
    part.scale(scale, center=(0.0, 0.0, 0.0))
    cams = apply(T_obj_world, origins) * scale
    center = (lo + hi) / 2 * scale
    rel = cams - center
    azimuths = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]))
    elevations = np.degrees(np.arcsin(rel[:, 2] / np.linalg.norm(rel, axis=1)))
    return ObjectModel(
        part,
        center,
        float(np.linalg.norm(hi - lo) / 2 * scale),
        (float(azimuths[0]), float(azimuths[-1])),
        float(np.median(elevations)),
        float(np.median(np.linalg.norm(rel, axis=1))),
    )


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_scanner (4, 4)`` of a scanner at ``eye (3,)`` looking at ``target (3,)`` in
    the camera convention (z forward, x right, y down, ``up`` up in the picture)."""
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return rigid(np.stack([x, np.cross(z, x), z], axis=1), eye)


def pinhole_directions(half_fov_deg: float, step_rad: float) -> np.ndarray:
    """Unit rays ``(K, 3)`` of a square pinhole grid (z forward) of half-angle
    ``half_fov_deg``, ``step_rad`` apart at the centre; row by row."""
    half = np.tan(np.radians(half_fov_deg))
    ticks = np.arange(-half, half + step_rad / 2, step_rad)
    u, v = np.meshgrid(ticks, ticks, indexing="xy")
    dirs = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def object_pair(
    angle_deg: float = 45.0,
    spacing: float = 5e-4,
    size: float = 0.2,
    noise: float = 1e-4,
    seed: int = 0,
    sequence: Path | None = None,
    cache: Path | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A simulated laser-scanner pair of a real object (:func:`object_model`).

    Two pinhole scanners on the arc the RGB-D camera covered (at its median elevation and
    distance), ``angle_deg`` apart in azimuth about the middle of the arc, look at the
    object's centre; rays ``spacing`` m apart at that distance, range noise of std ``noise``.

    Returns:
        ``(src (N, 3), tgt (M, 3), T_gt (4, 4))`` float64: each scan in its scanner's frame
        (z forward, y down, metres) and the transform mapping src's frame into tgt's.
    """
    model = object_model(sequence, size, cache)
    scene = raycasting_scene(model.mesh)
    a0, a1 = np.radians(model.azimuth_deg)
    middle = a0 + np.angle(np.exp(1j * (a1 - a0))) / 2
    elevation = np.radians(model.elevation_deg)
    poses = []
    for azimuth in (middle - np.radians(angle_deg) / 2, middle + np.radians(angle_deg) / 2):
        way = np.array(
            [
                np.cos(elevation) * np.cos(azimuth),
                np.cos(elevation) * np.sin(azimuth),
                np.sin(elevation),
            ]
        )
        poses.append(look_at(model.center + model.distance * way, model.center))
    half_fov = np.degrees(np.arctan(model.radius / model.distance)) * 1.05
    dirs = pinhole_directions(half_fov, spacing / model.distance)
    rng = np.random.default_rng([seed, 4])
    far = 2 * (model.distance + model.radius)
    src, tgt = (scan(scene, T, dirs, rng, noise, far) for T in poses)
    return src, tgt, relative(poses[0], poses[1])
