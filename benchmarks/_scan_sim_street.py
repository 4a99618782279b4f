"""The simulated street of benchmarks/scan_sim.py: a street scene (buildings, kerbs, poles and
lamps, parked cars, trees, the ground) as an Open3D mesh, ray-cast from a spinning LiDAR 1.8 m
above the road; scan B's sensor is 4 m ahead and turned 12 deg.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from _scan_sim_geometry import (
    Pair,
    quiet_open3d,
    raycasting_scene,
    relative,
    rigid,
    rotation_xyz,
    scan,
)

STREET_LENGTH = 80.0  # m, along x
ROAD_HALF_WIDTH = 5.0  # m; kerb and sidewalk from here to the building line
BUILDING_LINE = 8.0  # m from the street's axis
SENSOR_HEIGHT = 1.8  # m
LIDAR_FOV_DEG = (-25.0, 15.0)  # lowest and highest ring
LIDAR_MAX_RANGE = 100.0  # m
LIDAR_MIN_RANGE = 0.5  # m
RING_CHOICES = (16, 32, 64, 128)
STREET_VOXEL = 0.3  # m, the hand-set feature voxel for Open3D's FPFH on these scans


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
    o3d = quiet_open3d()
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
