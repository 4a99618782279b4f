"""The scanners and pairs of benchmarks/scan_sim.py's ``room`` set: a terrestrial laser scanner
(TLS: panoramic, 360 deg in azimuth, -60 to +90 deg in elevation, a few mm of range noise) or a
rotating 2D laser (a vertical 270 deg fan turned about the vertical axis: 1-3 cm of noise,
scan lines far apart), set up at positions 1-4 m apart in a room of `_scan_sim_room.py`.
Points are in the scanner's frame (x forward, z up), as a scanner writes them; a few mixed
pixels float along their rays.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from _scan_sim_geometry import (
    Pair,
    apply,
    cast,
    quiet_open3d,
    raycasting_scene,
    relative,
    rigid,
    rotation_xyz,
)
from _scan_sim_room import Room, room_mesh

SENSORS = ("tls", "line2d")
TLS_ELEVATION_DEG = (-60.0, 90.0)
LINE_FAN_DEG = 135.0  # half the 2D laser's fan, from the zenith
LINE_STEP_DEG = 0.25  # along a line of the 2D laser
ROOM_VOXEL = 0.1  # m, the hand-set voxel of Open3D's FPFH on the rooms (docs/rooms.md)
OUTLIER_SHARE = 5e-4  # of the returns: mixed pixels, somewhere along their ray


class Scanner(NamedTuple):
    """How a sensor samples and how noisy it is."""

    kind: str  # "tls" or "line2d"
    directions: np.ndarray  # (K, 3) unit rays in the sensor frame, in firing order
    noise: float  # m, std of the range noise at 0 m
    noise_per_m: float  # m of std added per m of range
    min_range: float  # m
    max_range: float  # m
    step_deg: float  # degrees between neighbouring rays across lines (TLS: both ways)


def tls_directions(step_deg: float, elevation_deg=TLS_ELEVATION_DEG) -> np.ndarray:
    """A TLS's rays ``(K, 3)``: columns every ``step_deg`` over the turn, each a column of
    elevations every ``step_deg`` over ``elevation_deg`` (x forward, z up); column by column."""
    azimuth = np.radians(np.arange(0.0, 360.0, step_deg))
    elevation = np.radians(np.arange(elevation_deg[0], elevation_deg[1] + 1e-9, step_deg))
    az, el = np.meshgrid(azimuth, elevation, indexing="ij")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(
        -1, 3
    )


def line2d_directions(line_step_deg: float, step_deg: float = LINE_STEP_DEG) -> np.ndarray:
    """A rotating 2D laser's rays ``(K, 3)``: a vertical fan of +-LINE_FAN_DEG from the zenith,
    ``step_deg`` apart, turned about z over half a turn in ``line_step_deg`` steps (each line
    covers both sides of the scanner); line by line."""
    azimuth = np.radians(np.arange(0.0, 180.0, line_step_deg))
    fan = np.radians(np.arange(-LINE_FAN_DEG, LINE_FAN_DEG + 1e-9, step_deg))
    az, phi = np.meshgrid(azimuth, fan, indexing="ij")
    horizontal = np.sin(phi)
    return np.stack([horizontal * np.cos(az), horizontal * np.sin(az), np.cos(phi)], -1).reshape(
        -1, 3
    )


def scanner(kind: str, points: int, share: float = 0.9) -> Scanner:
    """A ``kind`` scanner sampled for about ``points`` returns when ``share`` of its rays
    return: a TLS of 3 mm + 0.2 mm/m range noise; a rotating 2D laser of 1.2 cm + 0.5 cm/m."""
    if kind == "tls":
        span = (TLS_ELEVATION_DEG[1] - TLS_ELEVATION_DEG[0]) * 360.0
        step = float(np.sqrt(span * share / points))
        return Scanner(kind, tls_directions(step), 0.003, 2e-4, 0.4, 80.0, step)
    if kind == "line2d":
        per_line = 2 * LINE_FAN_DEG / LINE_STEP_DEG + 1
        step = 180.0 * per_line * share / points
        return Scanner(kind, line2d_directions(step), 0.012, 0.005, 0.1, 30.0, step)
    raise ValueError(f"sensor {kind!r}: not one of {', '.join(SENSORS)}")


def room_scan(scene, T_world_sensor: np.ndarray, sensor: Scanner,
              rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """``(N, 3)`` float64 returns of ``sensor`` at ``T_world_sensor (4, 4)`` in the sensor's
    frame: range noise growing with range, and OUTLIER_SHARE of the returns moved to a random
    share (20-95 %) of their range (mixed pixels, dust)."""
    dirs = sensor.directions
    t = cast(scene, T_world_sensor[:3, 3], dirs @ T_world_sensor[:3, :3].T)
    keep = np.isfinite(t) & (t >= sensor.min_range) & (t <= sensor.max_range)
    dirs, t = dirs[keep], t[keep]
    t = t + (sensor.noise + sensor.noise_per_m * t) * rng.standard_normal(len(t))
    stray = rng.random(len(t)) < OUTLIER_SHARE
    t[stray] *= rng.uniform(0.2, 0.95, int(stray.sum()))
    return dirs * t[:, None]


def _clear(scene, point: np.ndarray) -> float:
    """Distance (m) from ``point (3,)`` to the nearest surface of ``scene``."""
    o3d = quiet_open3d()
    query = o3d.core.Tensor(point[None].astype(np.float32))
    return float(scene.compute_distance(query).numpy()[0])


def positions(room: Room, scene, distance: float, rng: np.random.Generator,
              cross: bool = False) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Two scanner positions ``(3,)`` ``distance`` m apart on the floor of ``room``, each at
    least 0.45 m from every surface at 0.6 m and at the sensor's height (1.3-1.7 m above the
    floor); ``cross``: on the two sides of the partition wall."""
    L, W, _ = room.size
    for _ in range(20000):
        a = np.array([rng.uniform(0.5, L - 0.5), rng.uniform(0.5, W - 0.5), 0.0])
        turn = rng.uniform(0, 2 * np.pi)
        b = a + distance * np.array([np.cos(turn), np.sin(turn), 0.0])
        if cross and room.partition_x is not None:
            if (a[0] - room.partition_x) * (b[0] - room.partition_x) > 0:
                continue
        heights = rng.uniform(1.3, 1.7, 2)
        ok = True
        for p, h in ((a, heights[0]), (b, heights[1])):
            inside = 0.5 < p[0] < L - 0.5 and 0.5 < p[1] < W - 0.5
            if (
                not inside
                or min(_clear(scene, p + np.array([0.0, 0.0, z])) for z in (0.6, h)) < 0.45
            ):
                ok = False
                break
        if ok:
            up = np.array([0.0, 0.0, 1.0])
            return a + heights[0] * up, b + heights[1] * up
    raise RuntimeError(f"no two free positions {distance} m apart in the room")


def overlap(scene, src: np.ndarray, T_world_src: np.ndarray, T_world_tgt: np.ndarray,
            tol: float = 0.05) -> float:  # fmt: skip
    """Share of (up to 20000 of) ``src``'s points that the target's scanner sees: the ray from
    its position to the point hits the room within ``tol`` of it (its own field of view
    aside)."""
    pick = np.random.default_rng(0).permutation(len(src))[:20000]
    world = apply(T_world_src, src[pick])
    rays = world - T_world_tgt[:3, 3]
    dist = np.linalg.norm(rays, axis=1)
    hit = cast(scene, T_world_tgt[:3, 3], rays / dist[:, None])
    return float(np.mean(np.abs(hit - dist) < tol))


def room_pair(seed: int = 0, layout: str = "furnished", sensor: str = "tls",
              points: int = 200_000, distance: float = 2.0, cross: bool = False,
              pair_seed: int = 0) -> tuple[Pair, dict]:  # fmt: skip
    """A simulated pair of scans of the room ``room_mesh(seed, layout)``.

    Two ``sensor`` scanners (``"tls"`` or ``"line2d"``, about ``points`` returns each) stand
    ``distance`` m apart (``cross``: on the two sides of the partition wall), each levelled to
    within 0.05 deg (TLS) or 1 deg (2D laser) and turned to a random heading (``pair_seed``
    picks positions, headings and noise).

    Returns:
        ``((src (N, 3), tgt (M, 3), T_gt (4, 4)), info)``: each scan in its sensor frame
        (x forward, z up, metres), the transform mapping src's frame into tgt's, and how the
        pair was made (``info.json``: its ``size`` is the room's longest side, ``voxel`` the
        hand-set voxel of Open3D's FPFH, ``overlap`` the share of src the target's scanner sees).
    """
    room = room_mesh(seed, layout)
    scene = raycasting_scene(room.mesh)
    rng = np.random.default_rng([seed, pair_seed, 8])
    a, b = positions(room, scene, distance, rng, cross)
    tilt = 0.05 if sensor == "tls" else 1.0
    poses = [rigid(rotation_xyz(*rng.normal(0.0, tilt, 2), rng.uniform(0, 360)), p) for p in (a, b)]
    scan_with = scanner(sensor, points)
    src, tgt = (room_scan(scene, T, scan_with, rng) for T in poses)
    T_gt = relative(poses[0], poses[1])
    yaw = float(np.degrees(np.arccos(np.clip((np.trace(T_gt[:3, :3]) - 1) / 2, -1, 1))))
    info = {"kind": "room", "room_seed": seed, "layout": layout, "sensor": sensor,
            "pair_seed": pair_seed, "asked_points_per_scan": points, "distance_m": distance,
            "cross_partition": bool(cross and room.partition_x is not None),
            "rotation_deg": round(yaw, 3), "room_m": [round(v, 3) for v in room.size],
            "size": round(max(room.size[:2]), 3), "scene_size_m": round(max(room.size[:2]), 3),
            "step_deg": round(scan_with.step_deg, 4), "range_noise_m": scan_with.noise,
            "voxel": ROOM_VOXEL, "overlap": round(overlap(scene, src, *poses), 3)}  # fmt: skip
    return (src, tgt, T_gt), info


#: the default pairs of the ``room`` set: (name, room seed, layout, sensor, points, metres
#: apart, across the partition); rooms 2 and 5 are symmetric
ROOM_PAIRS = (
    ("r0-tls-1.5m", 0, "furnished", "tls", 200_000, 1.5, False),
    ("r0-tls-3.5m", 0, "furnished", "tls", 300_000, 3.5, False),
    ("r0-line-2m", 0, "furnished", "line2d", 150_000, 2.0, False),
    ("r1-tls-cross-2.5m", 1, "partition", "tls", 300_000, 2.5, True),
    ("r1-tls-1.2m", 1, "partition", "tls", 200_000, 1.2, False),
    ("r1-line-cross-3m", 1, "partition", "line2d", 120_000, 3.0, True),
    ("r2-sym-tls-2m", 2, "symmetric", "tls", 200_000, 2.0, False),
    ("r2-sym-tls-4m", 2, "symmetric", "tls", 300_000, 4.0, False),
    ("r2-sym-line-2.5m", 2, "symmetric", "line2d", 150_000, 2.5, False),
    ("r3-tls-3m-1M", 3, "furnished", "tls", 1_000_000, 3.0, False),
    ("r4-tls-cross-4m", 4, "partition", "tls", 500_000, 4.0, True),
    ("r4-line-1.5m", 4, "partition", "line2d", 100_000, 1.5, False),
    ("r5-sym-tls-3m", 5, "symmetric", "tls", 400_000, 3.0, False),
    ("r6-tls-2m-100k", 6, "furnished", "tls", 100_000, 2.0, False),
)
