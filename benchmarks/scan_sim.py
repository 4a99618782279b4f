"""Simulated scans with ground truth: spinning LiDAR of a street, laser scans of an object.

Development data that looks like the LiDAR and laser scans users bring, made deterministically
from a seed (``np.random.default_rng``; no global RNG):

* **street**: a street scene (buildings along both sides, some with recesses, kerbs, poles and
  street lamps, parked cars, trees, the ground) as an Open3D triangle mesh, about 80 m long,
  ray-cast from a spinning LiDAR 1.8 m above the road (16-128 rings over -25..+15 deg, an
  azimuth resolution picked for the asked number of points, 100 m range, 1.5 cm range noise).
  Points are in the sensor's frame, as a LiDAR writes them: the ring pattern is fixed to the
  sensor and the density falls with range. Scan B's sensor is 4 m ahead and turned 12 deg.
* **object**: a triangle mesh fused (TSDF, Open3D ``VoxelBlockGrid``) from a real RGB-D
  sequence (``rgbd/realsense_tabletop`` of the shared data: an open box with objects in it on
  a table), the table cut off, scaled to 20 cm, ray-cast by a dense pinhole laser scanner
  (0.5 mm spacing on the object, 0.1 mm range noise) from two viewpoints 45 deg apart on the
  arc the real camera covered. Points are in the scanner's frame (z forward, y down).
* **geo / hostile** variants of a pair: offsets of 1e3 .. 1e7 m (UTM-like), a stray point at
  1e6 m or 1e30 m, duplicated points, clouds scaled by 1e30 and 1e300, float32 coordinates at
  a 1e9 m offset.

Every pair is ``(src (N, 3) float64, tgt (M, 3) float64, T_gt (4, 4) float64)`` with
``T_gt`` mapping the source's frame into the target's (``x_tgt = R x_src + t``).

Usage::

    python benchmarks/scan_sim.py --out DIR [--sets street object geo hostile]
        [--sizes 42000 1100000] [--cache DIR] [--seed 0] [--preview]

writes each pair as ``DIR/<name>/{source.ply,target.ply,T_gt.txt,info.json}`` (float64 PLY
where float32 would lose more than a millionth of the cloud's size, else float32).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
OBJECT_SEQUENCE = "rgbd/realsense_tabletop"

STREET_LENGTH = 80.0  # m, along x
ROAD_HALF_WIDTH = 5.0  # m; kerb and sidewalk from here to the building line
BUILDING_LINE = 8.0  # m from the street's axis
SENSOR_HEIGHT = 1.8  # m
LIDAR_FOV_DEG = (-25.0, 15.0)  # lowest and highest ring
LIDAR_MAX_RANGE = 100.0  # m
LIDAR_MIN_RANGE = 0.5  # m
RING_CHOICES = (16, 32, 64, 128)
STREET_VOXEL = 0.3  # m, the hand-set feature voxel for Open3D's FPFH on these scans
OBJECT_VOXEL_FRACTION = 1 / 50  # of the object's size, the hand-set voxel for objects

GEO_OFFSETS = {
    "1e3": (1.0e3, 1.0e3, 0.0),
    "1e5": (1.0e5, 1.0e5, 0.0),
    "utm": (4.5e5, 5.2e6, 120.0),
    "1e6": (1.0e6, 1.0e6, 0.0),
    "1e7": (1.0e7, 1.0e7, 0.0),
}
SETS = ("street", "object", "geo", "hostile")

Pair = tuple[np.ndarray, np.ndarray, np.ndarray]  # src (N, 3), tgt (M, 3), T_gt (4, 4)


def _open3d():
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


# ====================================================================== transforms


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


# ====================================================================== ray casting


def raycasting_scene(mesh):
    """An ``open3d.t.geometry.RaycastingScene`` of a legacy ``TriangleMesh``."""
    o3d = _open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def cast(scene, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distances ``(N,)`` float64 along unit ``directions (N, 3)`` from ``origin (3,)`` to the
    first hit of ``scene`` (``inf`` where a ray hits nothing)."""
    o3d = _open3d()
    rays = np.empty((len(directions), 6), dtype=np.float32)
    rays[:, :3] = origin
    rays[:, 3:] = directions
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    return hits["t_hit"].numpy().astype(np.float64)


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


# ====================================================================== street scene


def _box(o3d, lo, hi):
    """A box mesh from corner ``lo (3,)`` to corner ``hi (3,)``."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    size = hi - lo
    box = o3d.geometry.TriangleMesh.create_box(size[0], size[1], size[2])
    return box.translate(lo)


def _cylinder(o3d, x: float, y: float, z0: float, radius: float, height: float):
    """A vertical cylinder mesh standing at ``(x, y, z0)``."""
    cyl = o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=12, split=1)
    return cyl.translate((x, y, z0 + height / 2))


def _sphere(o3d, center, radius: float):
    """A sphere mesh around ``center (3,)``."""
    return o3d.geometry.TriangleMesh.create_sphere(radius, resolution=10).translate(center)


def _buildings(o3d, rng: np.random.Generator, side: int, length: float) -> list:
    """Boxes of the buildings on one side (``side`` +1: y > 0): blocks 8-16 m wide, 6-22 m
    high, 8-14 m deep, set back 0-1.5 m from the building line, some with a 1-3 m recess in
    the middle of their front, and alleys of 2-5 m between some of them."""
    parts, x = [], -length / 2
    while x < length / 2 - 2:
        x1 = min(x + rng.uniform(8, 16), length / 2)
        depth, height = rng.uniform(8, 14), rng.uniform(6, 22)
        front = BUILDING_LINE + rng.uniform(0, 1.5)
        spans = [(x, x1, front)]
        if x1 - x > 7 and rng.random() < 0.4:
            a = x + rng.uniform(2, (x1 - x) / 2 - 1)
            b = a + rng.uniform(2, (x1 - x) / 2)
            spans = [(x, a, front), (a, b, front + rng.uniform(1, 3)), (b, x1, front)]
        for lo, hi, f in spans:
            y0, y1 = sorted((side * f, side * (front + depth)))
            parts.append(_box(o3d, (lo, y0, 0), (hi, y1, height)))
        x = x1 + (rng.uniform(2, 5) if rng.random() < 0.35 else 0.0)
    return parts


def _street_furniture(o3d, rng: np.random.Generator, side: int, length: float) -> list:
    """Poles (every 10-16 m, 5-8 m high, some with a lamp arm over the road), parked cars
    (body and cabin boxes, 0.25 m above the road) and trees (trunk and a crown of spheres)."""
    parts = []
    x = -length / 2 + rng.uniform(0, 6)
    while x < length / 2:
        y, h = side * (ROAD_HALF_WIDTH + 1.6), rng.uniform(5, 8)
        parts.append(_cylinder(o3d, x, y, 0.15, 0.1, h))
        if rng.random() < 0.6:
            y0, y1 = sorted((y, y - side * 1.6))
            parts.append(_box(o3d, (x - 0.06, y0, h - 0.1), (x + 0.06, y1, h + 0.05)))
        x += rng.uniform(10, 16)
    x = -length / 2 + rng.uniform(0, 5)
    while x < length / 2 - 5:
        car = rng.uniform(3.8, 4.8)
        if rng.random() < 0.6:
            yc = side * (ROAD_HALF_WIDTH - 1.1)
            parts.append(_box(o3d, (x, yc - 0.9, 0.25), (x + car, yc + 0.9, 1.0)))
            c0, c1 = x + 0.25 * car, x + 0.8 * car
            parts.append(_box(o3d, (c0, yc - 0.8, 1.0), (c1, yc + 0.8, 1.5)))
        x += car + rng.uniform(0.8, 6)
    for _ in range(3):
        x, y = rng.uniform(-length / 2, length / 2), side * (ROAD_HALF_WIDTH + 2.2)
        parts.append(_cylinder(o3d, x, y, 0.15, 0.15, 3.0))
        for _ in range(int(rng.integers(3, 6))):
            center = (x + rng.uniform(-1, 1), y + rng.uniform(-0.8, 0.8), 3.5 + rng.uniform(0, 1.5))
            parts.append(_sphere(o3d, center, rng.uniform(0.8, 1.6)))
    return parts


def street_mesh(seed: int = 0, length: float = STREET_LENGTH):
    """The street scene as a legacy Open3D ``TriangleMesh`` in the world frame (x along the
    street, z up, the road's surface at z = 0): the ground (140 x 80 m), sidewalks 0.15 m
    high, buildings, poles, parked cars and trees on both sides; ``seed`` picks them."""
    o3d = _open3d()
    rng = np.random.default_rng([seed, 1])
    parts = [_box(o3d, (-length / 2 - 30, -40, -0.2), (length / 2 + 30, 40, 0))]
    for side in (-1, 1):
        y0, y1 = sorted((side * ROAD_HALF_WIDTH, side * BUILDING_LINE))
        parts.append(_box(o3d, (-length / 2 - 30, y0, 0), (length / 2 + 30, y1, 0.15)))
        parts += _buildings(o3d, rng, side, length)
        parts += _street_furniture(o3d, rng, side, length)
    mesh = o3d.geometry.TriangleMesh()
    for part in parts:
        mesh += part
    return mesh


def lidar_directions(rings: int, azimuth_steps: int, fov_deg=LIDAR_FOV_DEG) -> np.ndarray:
    """Unit beam directions ``(azimuth_steps * rings, 3)`` of a spinning LiDAR in its frame
    (x forward, z up): ``rings`` elevations evenly over ``fov_deg``, ``azimuth_steps`` evenly
    over the turn; ordered by azimuth, then ring (the order of the sensor's firings)."""
    elevation = np.radians(np.linspace(fov_deg[0], fov_deg[1], rings))
    azimuth = 2 * np.pi * np.arange(azimuth_steps) / azimuth_steps
    az, el = np.meshgrid(azimuth, elevation, indexing="ij")
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    return dirs.reshape(-1, 3)


def street_poses(seed: int = 0, shift: float = 4.0, yaw_deg: float = 12.0):
    """``(T_world_a, T_world_b)``, two ``(4, 4)`` LiDAR poses: ``a`` in the right lane at
    x = -6 m, 1.8 m high, facing along the street with a mount tilt of a few tenths of a
    degree (seeded); ``b`` is ``shift`` m ahead of ``a`` along its heading, turned by
    ``yaw_deg``."""
    rng = np.random.default_rng([seed, 2])
    roll, pitch = rng.normal(0.0, 0.4, 2)
    T_world_a = rigid(rotation_xyz(roll, pitch, 0.0), (-6.0, -1.5, SENSOR_HEIGHT))
    motion = rigid(rotation_xyz(0.0, 0.0, yaw_deg), (shift, 0.0, 0.0))
    return T_world_a, T_world_a @ motion


def lidar_pattern(scene, poses, points_per_scan: int, rings: int | None = None) -> tuple[int, int]:
    """``(rings, azimuth_steps)`` for about ``points_per_scan`` returns per scan from each of
    ``poses`` (4x4 each): 16 rings up to 15k points, 32 up to 60k, 64 up to 250k, else 128
    (or ``rings``); the azimuth steps from the share of beams that return, measured with 360
    steps."""
    if rings is None:
        most = (15e3, 60e3, 250e3, np.inf)  # points per scan of each ring count
        rings = next(r for r, n in zip(RING_CHOICES, most, strict=True) if points_per_scan <= n)
    probe = lidar_directions(rings, 360)
    rng = np.random.default_rng(0)
    returned = [
        len(scan(scene, T, probe, rng, 0.0, LIDAR_MAX_RANGE, LIDAR_MIN_RANGE)) for T in poses
    ]
    share = max(float(np.mean(returned)) / len(probe), 1e-3)
    return rings, max(8, round(points_per_scan / (rings * share)))


class StreetScans(NamedTuple):
    """A simulated LiDAR pair and how it was made."""

    src: np.ndarray  # (N, 3) float64, scan a in its sensor frame
    tgt: np.ndarray  # (M, 3) float64, scan b in its sensor frame
    T_gt: np.ndarray  # (4, 4) maps a's sensor frame into b's
    T_world_src: np.ndarray  # (4, 4) pose of sensor a in the scene
    T_world_tgt: np.ndarray  # (4, 4) pose of sensor b in the scene
    rings: int
    azimuth_steps: int
    mesh: object  # the scene, a legacy open3d TriangleMesh


def simulate_street(
    points_per_scan: int,
    rings: int | None = None,
    seed: int = 0,
    shift: float = 4.0,
    yaw_deg: float = 12.0,
    noise: float = 0.015,
) -> StreetScans:
    """Two LiDAR scans of the street of ``seed`` (see :func:`street_pair`) with the scene,
    the sensor poses and the pattern."""
    mesh = street_mesh(seed)
    scene = raycasting_scene(mesh)
    T_world_a, T_world_b = street_poses(seed, shift, yaw_deg)
    rings, steps = lidar_pattern(scene, (T_world_a, T_world_b), points_per_scan, rings)
    dirs = lidar_directions(rings, steps)
    rng = np.random.default_rng([seed, 3])
    src, tgt = (
        scan(scene, T, dirs, rng, noise, LIDAR_MAX_RANGE, LIDAR_MIN_RANGE)
        for T in (T_world_a, T_world_b)
    )
    return StreetScans(
        src, tgt, relative(T_world_a, T_world_b), T_world_a, T_world_b, rings, steps, mesh
    )


def street_pair(
    points_per_scan: int,
    rings: int | None = None,
    seed: int = 0,
    shift: float = 4.0,
    yaw_deg: float = 12.0,
    noise: float = 0.015,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A simulated spinning-LiDAR pair of a street.

    Args:
        points_per_scan: about how many returns each scan has (within a few percent).
        rings: 16, 32, 64 or 128 (None: picked from ``points_per_scan``).
        seed: picks the scene, the sensor's tilt and the range noise.
        shift, yaw_deg: scan b's sensor is ``shift`` m ahead of a's and turned ``yaw_deg``.
        noise: std of the range noise (m).

    Returns:
        ``(src (N, 3), tgt (M, 3), T_gt (4, 4))`` float64: each scan in its sensor frame
        (x forward, z up, metres) and the transform mapping src's frame into tgt's.
    """
    sim = simulate_street(points_per_scan, rings, seed, shift, yaw_deg, noise)
    return sim.src, sim.tgt, sim.T_gt


def street_settings(points_per_scan: int, seed: int = 0, shift: float = 4.0,
                    yaw_deg: float = 12.0) -> dict:  # fmt: skip
    """What makes a street pair, as its ``info.json`` records it."""
    return {"kind": "street", "asked_points_per_scan": points_per_scan, "seed": seed,
            "shift_m": shift, "yaw_deg": yaw_deg}  # fmt: skip


def made_street(
    points_per_scan: int, seed: int = 0, shift: float = 4.0, yaw_deg: float = 12.0
) -> tuple[Pair, dict]:
    """``((src, tgt, T_gt), info)``: :func:`street_pair` and how it was made (the settings,
    the pattern, the scene's length and the hand-set voxel for Open3D's FPFH)."""
    sim = simulate_street(points_per_scan, seed=seed, shift=shift, yaw_deg=yaw_deg)
    info = {**street_settings(points_per_scan, seed, shift, yaw_deg), "rings": sim.rings,
            "azimuth_steps": sim.azimuth_steps, "scene_size_m": STREET_LENGTH,
            "voxel": STREET_VOXEL}  # fmt: skip
    return (sim.src, sim.tgt, sim.T_gt), info


# ====================================================================== object scans


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
    o3d = _open3d()
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
    o3d = _open3d()
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


# ====================================================================== variants


def georeferenced(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, offset) -> Pair:
    """Both clouds ``(N, 3)``, ``(M, 3)`` shifted by ``offset (3,)`` and ``T (4, 4)``
    conjugated so that it still maps the shifted source onto the shifted target:
    ``T' = Tr(o) T Tr(-o)``."""
    o = np.asarray(offset, dtype=np.float64)
    T_new = translation(o) @ T @ translation(-o)
    return src + o, tgt + o, T_new


def scaled(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, factor: float) -> Pair:
    """Both clouds multiplied by ``factor``; ``T``'s translation too."""
    T_new = T.copy()
    T_new[:3, 3] *= factor
    return src * factor, tgt * factor, T_new


def with_stray_point(
    src: np.ndarray, tgt: np.ndarray, T: np.ndarray, distance: float, seed: int = 0
) -> Pair:
    """One point appended to each cloud, ``distance`` from its origin in a seeded direction
    (a different one per cloud); ``T`` stays right for the others. ``(N + 1, 3)``,
    ``(M + 1, 3)``."""
    rng = np.random.default_rng([seed, 5])
    ways = rng.standard_normal((2, 3))
    ways *= distance / np.linalg.norm(ways, axis=1, keepdims=True)
    return np.vstack([src, ways[:1]]), np.vstack([tgt, ways[1:]]), T


def with_duplicates(
    src: np.ndarray,
    tgt: np.ndarray,
    T: np.ndarray,
    distinct: int = 10,
    repeats: int = 2000,
    only: bool = False,
    seed: int = 0,
) -> Pair:
    """``distinct`` seeded points of each cloud, each repeated ``repeats`` times, appended to
    that cloud (``only``: the clouds are those repeats alone, the target's being the source's
    points mapped by ``T``, so that ``T`` is exact)."""
    rng = np.random.default_rng([seed, 6])
    pick_src = src[rng.choice(len(src), distinct, replace=False)]
    if only:
        return np.repeat(pick_src, repeats, axis=0), np.repeat(apply(T, pick_src), repeats, 0), T
    pick_tgt = tgt[rng.choice(len(tgt), distinct, replace=False)]
    return (
        np.vstack([src, np.repeat(pick_src, repeats, axis=0)]),
        np.vstack([tgt, np.repeat(pick_tgt, repeats, axis=0)]),
        T,
    )


class Variant(NamedTuple):
    """A named change of a pair: ``make(src, tgt, T) -> (src, tgt, T)``; ``dtype`` forces the
    PLY's coordinate type (None: the smallest exact one); ``voxel_factor`` scales the
    hand-set voxel."""

    make: object
    dtype: str | None = None
    voxel_factor: float = 1.0


def geo_variants() -> dict[str, Variant]:
    """``geo-<name>``: the pair moved to the offsets of ``GEO_OFFSETS``."""
    return {
        f"geo-{name}": Variant(lambda s, t, T, o=offset: georeferenced(s, t, T, o))
        for name, offset in GEO_OFFSETS.items()
    }


def hostile_variants() -> dict[str, Variant]:
    """The hostile inputs: stray points, duplicates, huge scales, float32 at 1e9 m."""
    return {
        "stray-1e6": Variant(lambda s, t, T: with_stray_point(s, t, T, 1e6)),
        "stray-1e30": Variant(lambda s, t, T: with_stray_point(s, t, T, 1e30)),
        "dup-added": Variant(lambda s, t, T: with_duplicates(s, t, T)),
        "dup-only": Variant(lambda s, t, T: with_duplicates(s, t, T, only=True)),
        "scale-1e30": Variant(lambda s, t, T: scaled(s, t, T, 1e30), voxel_factor=1e30),
        "scale-1e300": Variant(lambda s, t, T: scaled(s, t, T, 1e300), voxel_factor=1e300),
        "f32-1e9": Variant(lambda s, t, T: georeferenced(s, t, T, (1e9, 1e9, 0.0)), "f4"),
    }


# ====================================================================== writing


def ply_dtype(points: np.ndarray) -> str:
    """``"f4"`` when float32 keeps ``points (N, 3)`` within a millionth of the cloud's size
    (the spread between its 1st and 99th percentiles), else ``"f8"``."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return "f4"
    with np.errstate(over="ignore"):
        as32 = points.astype(np.float32).astype(np.float64)
    if not np.all(np.isfinite(as32)):
        return "f8"
    spread = np.percentile(points, 99, axis=0) - np.percentile(points, 1, axis=0)
    size = float(np.linalg.norm(spread))
    error = float(np.max(np.abs(as32 - points)))
    return "f4" if error <= 1e-6 * size or error == 0.0 else "f8"


def write_ply(path: Path, points: np.ndarray, dtype: str | None = None) -> str:
    """Write ``points (N, 3)`` as a binary PLY of x, y, z of ``dtype`` (``"f4"`` float,
    ``"f8"`` double; None: :func:`ply_dtype`); returns the dtype written."""
    from plyfile import PlyData, PlyElement

    dtype = dtype or ply_dtype(points)
    vertex = np.empty(len(points), dtype=[("x", dtype), ("y", dtype), ("z", dtype)])
    with np.errstate(over="ignore"):
        for k, axis in enumerate("xyz"):
            vertex[axis] = points[:, k]
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    return dtype


def write_pair(folder: Path, pair: Pair, info: dict, dtype: str | None = None) -> dict:
    """``folder/{source.ply,target.ply,T_gt.txt,info.json}``; ``info`` (how it was made) gets
    the point counts and PLY types; returns it."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    src, tgt, T = pair
    info = {**info, "points_src": len(src), "points_tgt": len(tgt)}
    info["ply_dtype"] = [
        write_ply(folder / "source.ply", src, dtype),
        write_ply(folder / "target.ply", tgt, dtype),
    ]
    np.savetxt(folder / "T_gt.txt", T, fmt="%.17g")
    (folder / "info.json").write_text(json.dumps(info, indent=1) + "\n")
    return info


def size_name(points: int) -> str:
    """``42000 -> "42k"``, ``1100000 -> "1.1M"``, ``500 -> "500"``."""
    for unit, div in (("M", 1e6), ("k", 1e3)):
        if points >= div:
            return f"{points / div:.3g}{unit}"
    return str(points)


def top_view(points: np.ndarray, path: Path, title: str = "", extent: float = 60.0) -> None:
    """A PNG of ``points (N, 3)`` seen from above (x right, y up), coloured by height, within
    ``extent`` m of the origin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    near = np.all(np.abs(points[:, :2]) < extent, axis=1)
    p = points[near][np.argsort(points[near, 2])]
    span = np.ptp(p[:, :2], axis=0) + 1e-9
    fig, ax = plt.subplots(figsize=(16, max(4.0, 16 * span[1] / span[0])))
    dots = ax.scatter(p[:, 0], p[:, 1], c=p[:, 2], s=0.5, cmap="turbo", linewidths=0)
    fig.colorbar(dots, ax=ax, label="height (sensor frame)", shrink=0.6)
    ax.set_aspect("equal")
    ax.set_title(f"{title} ({len(points)} points)")
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


# ====================================================================== main


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the pairs")
    parser.add_argument(
        "--sets",
        nargs="+",
        default=list(SETS),
        metavar="SET",
        help=f"of {', '.join(SETS)} (default: all)",
    )
    parser.add_argument(
        "--sizes",
        nargs="+",
        type=int,
        default=[42000, 1100000],
        help="points per scan of the street pairs",
    )
    parser.add_argument(
        "--variants-of",
        nargs="+",
        default=["street"],
        choices=("street", "object"),
        help="pairs the geo and hostile variants are made of: the street at the "
        "first --sizes, the object (default: street)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shift", type=float, default=4.0, help="street: metres between scans")
    parser.add_argument("--yaw", type=float, default=12.0, help="street: degrees between scans")
    parser.add_argument(
        "--angles",
        nargs="+",
        type=float,
        default=[45.0],
        help="object: degrees between the two viewpoints",
    )
    parser.add_argument("--data", type=Path, default=DATA, help="the shared data folder")
    parser.add_argument("--cache", type=Path, help="folder for the fused object mesh")
    parser.add_argument(
        "--preview", action="store_true", help="also a top-view PNG of each street pair's source"
    )
    args = parser.parse_args(argv)
    unknown = sorted(set(args.sets) - set(SETS))
    if unknown:
        parser.error(f"--sets {unknown[0]!r}: not one of {', '.join(SETS)}")
    if args.cache is not None and args.cache.resolve().is_relative_to(ROOT):
        parser.error(f"--cache {args.cache}: inside the repository; give a folder outside it")
    if "object" in args.sets or "object" in args.variants_of:
        if not (args.data / OBJECT_SEQUENCE).is_dir():
            parser.error(f"--data {args.data}: no {OBJECT_SEQUENCE} (the object's RGB-D video)")
    if not set(args.sets) & {"street", "geo", "hostile"} and "street" in args.variants_of:
        args.variants_of = [v for v in args.variants_of if v != "street"]
    return args


def _bases(args: argparse.Namespace) -> dict[str, tuple[Pair, dict]]:
    """The pairs of the sets asked: street pairs by size, object pairs by angle, with info."""
    pairs: dict[str, tuple[Pair, dict]] = {}
    want_street = "street" in args.sets or "street" in args.variants_of
    sizes = args.sizes if "street" in args.sets else args.sizes[:1]
    for n in sizes if want_street else []:
        pairs[f"street-{size_name(n)}"] = made_street(n, args.seed, args.shift, args.yaw)
    want_object = "object" in args.sets or "object" in args.variants_of
    for angle in args.angles if want_object else []:
        sequence = args.data / OBJECT_SEQUENCE
        pair = object_pair(angle, seed=args.seed, sequence=sequence, cache=args.cache)
        info = {"kind": "object", "angle_deg": angle, "seed": args.seed, "scene_size_m": 0.2,
                "voxel": 0.2 * OBJECT_VOXEL_FRACTION, "sequence": OBJECT_SEQUENCE}  # fmt: skip
        pairs[f"object-{angle:g}deg"] = (pair, info)
    return pairs


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    bases = _bases(args)
    variants: dict[str, Variant] = {}
    if "geo" in args.sets:
        variants.update(geo_variants())
    if "hostile" in args.sets:
        variants.update(hostile_variants())
    for name, (pair, info) in bases.items():
        if info["kind"] in args.sets:
            written = write_pair(args.out / name, pair, info)
            print(
                f"{name}: {written['points_src']} + {written['points_tgt']} points, "
                f"{written['ply_dtype'][0]}",
                file=sys.stderr,
            )
            if args.preview and info["kind"] == "street":
                top_view(pair[0], args.out / name / "top.png", name)
        first = next(k for k, (_, i) in bases.items() if i["kind"] == info["kind"])
        if info["kind"] not in args.variants_of or name != first:
            continue
        for suffix, variant in variants.items():
            new_info = {
                **info,
                "variant": suffix,
                "of": name,
                "voxel": info["voxel"] * variant.voxel_factor,
            }
            written = write_pair(
                args.out / f"{name}-{suffix}", variant.make(*pair), new_info, variant.dtype
            )
            print(
                f"{name}-{suffix}: {written['points_src']} + {written['points_tgt']} points, "
                f"{written['ply_dtype'][0]}",
                file=sys.stderr,
            )


if __name__ == "__main__":
    main()
