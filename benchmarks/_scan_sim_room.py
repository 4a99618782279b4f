"""The furnished rooms of benchmarks/scan_sim.py's ``room`` set: a room mesh (floor, ceiling, walls
with door and window openings, an optional partition wall, tables, shelves, chairs, boxes,
cylinders) made from a seed; a symmetric layout repeats its furniture turned 180 deg about the
room's centre. The scanners and pairs are `_scan_sim_room_scan.py`'s.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np

from _scan_sim_geometry import quiet_open3d
from _scan_sim_street import _box, _cylinder

WALL = 0.15  # m, wall, floor and ceiling thickness
LAYOUTS = ("furnished", "partition", "symmetric")


class Room(NamedTuple):
    """A room mesh and what a scan position needs to know of it."""

    mesh: object  # legacy open3d TriangleMesh, world frame: floor z = 0, room x in [0, L]
    size: tuple[float, float, float]  # length (x), width (y), height (z), m
    layout: str  # one of LAYOUTS
    partition_x: float | None  # x of the partition wall (None: none)


def _yawed_box(o3d, center, size, yaw: float):
    """A box of ``size (3,)`` whose bottom centre is ``center (3,)``, turned ``yaw`` rad about z."""
    sx, sy, sz = size
    box = o3d.geometry.TriangleMesh.create_box(sx, sy, sz).translate((-sx / 2, -sy / 2, 0.0))
    R = o3d.geometry.get_rotation_matrix_from_xyz((0.0, 0.0, yaw))
    return box.rotate(R, center=(0.0, 0.0, 0.0)).translate(center)


def _local(center, yaw: float, dx: float, dy: float, z: float = 0.0) -> np.ndarray:
    """The point ``(dx, dy)`` of a piece's own frame (turned ``yaw`` about its ``center``)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([center[0] + c * dx - s * dy, center[1] + s * dx + c * dy, z])


def table(o3d, center, yaw: float, rng: np.random.Generator) -> list:
    """A table: a top 0.72-0.78 m high, 1.2-1.8 x 0.7-0.9 m, on four legs."""
    lx, ly, h = rng.uniform(1.2, 1.8), rng.uniform(0.7, 0.9), rng.uniform(0.72, 0.78)
    parts = [_yawed_box(o3d, (center[0], center[1], h - 0.04), (lx, ly, 0.04), yaw)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            foot = _local(center, yaw, sx * (lx / 2 - 0.06), sy * (ly / 2 - 0.06))
            parts.append(_yawed_box(o3d, foot, (0.05, 0.05, h - 0.04), yaw))
    return parts


def chair(o3d, center, yaw: float, rng: np.random.Generator) -> list:
    """A chair: a seat 0.45 m high on four legs and a back 0.4-0.5 m high."""
    w = rng.uniform(0.42, 0.5)
    parts = [_yawed_box(o3d, (center[0], center[1], 0.42), (w, w, 0.04), yaw)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            foot = _local(center, yaw, sx * (w / 2 - 0.03), sy * (w / 2 - 0.03))
            parts.append(_yawed_box(o3d, foot, (0.03, 0.03, 0.42), yaw))
    back = _local(center, yaw, -w / 2 + 0.015, 0.0, 0.46)
    parts.append(_yawed_box(o3d, back, (0.03, w, rng.uniform(0.4, 0.5)), yaw))
    return parts


def shelf(o3d, center, yaw: float, rng: np.random.Generator) -> list:
    """A shelf (its back at ``center``, facing its local +x): two sides, a back and 4-6
    boards, 0.8-1.2 m wide, 0.3-0.4 m deep, 1.6-2.2 m high, some boxes on the boards."""
    w, d, h = rng.uniform(0.8, 1.2), rng.uniform(0.3, 0.4), rng.uniform(1.6, 2.2)
    parts = [_yawed_box(o3d, _local(center, yaw, 0.01, 0.0), (0.02, w, h), yaw)]
    for sy in (-1, 1):
        side = _local(center, yaw, d / 2, sy * (w / 2 - 0.01))
        parts.append(_yawed_box(o3d, side, (d, 0.02, h), yaw))
    boards = int(rng.integers(4, 7))
    for k in range(boards):
        z = 0.05 + k * (h - 0.1) / (boards - 1)
        parts.append(_yawed_box(o3d, _local(center, yaw, d / 2, 0.0, z), (d, w, 0.02), yaw))
        if k < boards - 1 and rng.random() < 0.6:
            bw = rng.uniform(0.15, w / 2)
            spot = _local(center, yaw, d / 2, rng.uniform(-w / 2 + bw, w / 2 - bw) / 2, z + 0.02)
            high = min(rng.uniform(0.1, 0.3), (h - 0.1) / (boards - 1) - 0.04)
            parts.append(_yawed_box(o3d, spot, (d * 0.8, bw, high), yaw))
    return parts


def boxes(o3d, center, yaw: float, rng: np.random.Generator) -> list:
    """One to three boxes of 0.3-0.8 m stacked on the floor, each turned a little."""
    parts, z = [], 0.0
    for _ in range(int(rng.integers(1, 4))):
        size = rng.uniform(0.3, 0.8, 3) * (1.0 if z == 0 else 0.7)
        size[2] = min(size[2], 0.6)
        turn = yaw + rng.uniform(-0.3, 0.3)
        parts.append(_yawed_box(o3d, (center[0], center[1], z), size, turn))
        z += size[2]
    return parts


def cylinder(o3d, center, yaw: float, rng: np.random.Generator) -> list:
    """A bin or a column: radius 0.12-0.3 m, 0.4-1.2 m high."""
    radius, height = rng.uniform(0.12, 0.3), rng.uniform(0.4, 1.2)
    return [_cylinder(o3d, center[0], center[1], 0.0, radius, height)]


PIECES = {"table": (table, 1.0), "chair": (chair, 0.4), "shelf": (shelf, 0.7),
          "boxes": (boxes, 0.5), "cylinder": (cylinder, 0.35)}  # fmt: skip


def _wall(o3d, axis: int, at: float, span: tuple[float, float], height: float,
          openings: list[tuple[float, float, float, float]]) -> list:  # fmt: skip
    """A wall of thickness WALL whose inner face is at ``at`` across ``axis`` (0: a wall at
    x = at, running along y), from ``span[0]`` to ``span[1]`` along the other axis, with
    ``openings`` ``(start, end, bottom, top)`` cut out of it (a door or a window: no return)."""
    cuts = sorted({span[0], span[1], *(v for o in openings for v in o[:2])})
    parts = []
    for a, b in itertools.pairwise(cuts):
        mid = (a + b) / 2
        gaps = [o for o in openings if o[0] <= mid <= o[1]]
        bands = [(0.0, height)] if not gaps else [(0.0, gaps[0][2]), (gaps[0][3], height)]
        for z0, z1 in bands:
            if z1 - z0 < 1e-6:
                continue
            lo, hi = [0.0, 0.0, z0], [0.0, 0.0, z1]
            lo[1 - axis], hi[1 - axis] = a, b
            outward = -1.0 if at <= 0 else 1.0
            lo[axis], hi[axis] = sorted((at, at + outward * WALL))
            parts.append(_box(o3d, lo, hi))
    return parts


def _openings(rng: np.random.Generator, length: float, height: float, door: bool) -> list:
    """A door (0.9 x 2.1 m) and/or windows (1-1.8 m wide, 0.9 m up to 2.2 m) along a wall."""
    out = []
    if door:
        a = rng.uniform(0.4, length - 1.3)
        out.append((a, a + 0.9, 0.0, 2.1))
    for _ in range(int(rng.integers(0, 3))):
        w = rng.uniform(1.0, 1.8)
        a = rng.uniform(0.3, length - w - 0.3)
        if all(a + w < o[0] - 0.2 or a > o[1] + 0.2 for o in out):
            out.append((a, a + w, 0.9, min(2.2, height - 0.2)))
    return out


def room_mesh(seed: int = 0, layout: str = "furnished") -> Room:
    """A furnished room of ``seed``: 5-9 x 4-7 m, 2.6-3.2 m high, a door and some windows in
    its walls (a corridor wall 1.5 m behind each door), furniture along the walls and in the
    room; ``partition`` adds a wall from one long side across 45-65 % of the width (an L-shaped
    space: scans on its two sides overlap less); ``symmetric`` places every piece twice, turned
    180 deg about the room's centre, with a symmetric door and windows, and one small box."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout {layout!r}: not one of {', '.join(LAYOUTS)}")
    o3d = quiet_open3d()
    rng = np.random.default_rng([seed, 7])
    L, W, H = rng.uniform(5.0, 9.0), rng.uniform(4.0, 7.0), rng.uniform(2.6, 3.2)
    parts = [_box(o3d, (-WALL, -WALL, -WALL), (L + WALL, W + WALL, 0.0)),
             _box(o3d, (-WALL, -WALL, H), (L + WALL, W + WALL, H + WALL))]  # fmt: skip
    sym = layout == "symmetric"
    walls = {}
    walls[(1, 0.0)] = _openings(rng, L, H, door=True)
    walls[(1, W)] = [(L - b, L - a, z0, z1) for a, b, z0, z1 in walls[(1, 0.0)]] if sym else (
        _openings(rng, L, H, door=False))  # fmt: skip
    walls[(0, 0.0)] = _openings(rng, W, H, door=False)
    walls[(0, L)] = [(W - b, W - a, z0, z1) for a, b, z0, z1 in walls[(0, 0.0)]] if sym else (
        _openings(rng, W, H, door=rng.random() < 0.3))  # fmt: skip
    for (axis, at), openings in walls.items():
        span = (-WALL, (W if axis == 0 else L) + WALL)
        parts += _wall(o3d, axis, at, span, H, openings)
        for a, b, z0, _ in openings:
            if z0 == 0.0:  # a door: the corridor's far wall
                out = at - 1.5 if at <= 0 else at + 1.5
                lo, hi = [a - 1.0, a - 1.0, 0.0], [b + 1.0, b + 1.0, H]
                lo[axis], hi[axis] = sorted((out, out + (-WALL if at <= 0 else WALL)))
                parts.append(_box(o3d, lo, hi))
    partition = None
    if layout == "partition":
        partition = float(rng.uniform(0.4, 0.6) * L)
        reach = float(rng.uniform(0.45, 0.65) * W)
        parts.append(_box(o3d, (partition, W - reach, 0.0), (partition + 0.1, W, H)))
    taken: list[tuple[float, float, float]] = []  # (x, y, radius) of the pieces placed

    def free(x, y, r):
        inside = r < x < L - r and r < y < W - r
        clear_wall = partition is None or not (partition - r < x < partition + 0.1 + r)
        return inside and clear_wall and all(np.hypot(x - a, y - b) > r + c for a, b, c in taken)

    names = list(PIECES)
    weights = np.array([PIECES[n][1] for n in names])
    count = int(rng.integers(7, 12)) // (2 if sym else 1)
    for _ in range(count * 20):
        if len(taken) >= count * (2 if sym else 1):
            break
        name = names[rng.choice(len(names), p=weights / weights.sum())]
        radius = {"table": 0.9, "shelf": 0.6, "chair": 0.35, "boxes": 0.45, "cylinder": 0.3}[name]
        if name == "shelf":  # against a wall, facing the room
            side = int(rng.integers(4))
            along = rng.uniform(0.7, (L if side < 2 else W) - 0.7)
            x, y, yaw = [(along, 0.02, np.pi / 2), (along, W - 0.02, -np.pi / 2),
                         (0.02, along, 0.0), (L - 0.02, along, np.pi)][side]  # fmt: skip
            cx, cy = x + 0.2 * np.cos(yaw), y + 0.2 * np.sin(yaw)
        else:
            x, y = rng.uniform(0.5, L - 0.5), rng.uniform(0.5, W - 0.5)
            yaw = rng.uniform(0, 2 * np.pi) if name != "table" else rng.choice([0.0, np.pi / 2])
            cx, cy = x, y
        spots = [(x, y, yaw, cx, cy)]
        if sym:
            spots.append((L - x, W - y, yaw + np.pi, L - cx, W - cy))
        if not all(free(sx, sy, radius - 0.2 * (name == "shelf")) for _, _, _, sx, sy in spots):
            continue
        if sym and np.hypot(spots[0][3] - L / 2, spots[0][4] - W / 2) < 2 * radius:
            continue
        state = rng.bit_generator.state
        for px, py, pyaw, sx, sy in spots:
            rng.bit_generator.state = state  # the twin gets the same sizes
            parts += PIECES[name][0](o3d, (px, py), pyaw, rng)
            taken.append((sx, sy, radius))
    if sym:  # what tells the two halves apart: one box of 0.3-0.5 m
        for _ in range(50):
            x, y = rng.uniform(0.5, L - 0.5), rng.uniform(0.5, W - 0.5)
            if free(x, y, 0.3):
                size = (*rng.uniform(0.3, 0.5, 2), rng.uniform(0.3, 0.5))
                parts.append(_yawed_box(o3d, (x, y, 0.0), size, rng.uniform(0, np.pi)))
                taken.append((x, y, 0.3))
                break
    mesh = o3d.geometry.TriangleMesh()
    for part in parts:
        mesh += part
    return Room(mesh, (float(L), float(W), float(H)), layout, partition)
