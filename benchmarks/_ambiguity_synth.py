"""The ``synthetic`` set of benchmarks/ambiguity.py: a tiny room with two identical cabinets
1.5 m apart, seen by two views, and correspondences made without features (the script's test
runs on it in seconds).

The source view sees the floor, the wall and cabinet A; the target view sees both cabinets.
``clean``: true correspondences on cabinet A among random outliers; ``slid``: as many again
from cabinet A in the source to cabinet B in the target (what repeated structure gives the
features), so the correspondences support a pose slid 1.5 m along the wall as well.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

#: the cabinets' offset along the wall (metres)
SLIDE = 1.5
VOXEL = 0.025


class SynthPair(NamedTuple):
    name: str
    source: torch.Tensor  # (N, 3) full points
    target: torch.Tensor  # (M, 3)
    kept_source: torch.Tensor  # (n, 3) the "kept" points (every 4th)
    kept_target: torch.Tensor
    correspondences: tuple[torch.Tensor, torch.Tensor, torch.Tensor]
    T_gt: torch.Tensor  # (4, 4) source -> target


def _box(corner, size, step, g):
    """Points on the five visible faces of an axis-aligned box (no bottom)."""
    x0, y0, z0 = corner
    sx, sy, sz = size
    faces = []
    for axis, (a, b) in ((0, (sy, sz)), (1, (sx, sz)), (2, (sx, sy))):
        n = int(a * b / step**2)
        uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([a, b])
        for level in (0.0, size[axis]) if axis < 2 else (size[axis],):
            pts = torch.empty(n, 3, dtype=torch.float64)
            others = [k for k in range(3) if k != axis]
            pts[:, axis] = level
            pts[:, others[0]], pts[:, others[1]] = uv[:, 0], uv[:, 1]
            faces.append(pts)
    return torch.cat(faces) + torch.tensor([x0, y0, z0], dtype=torch.float64)


def _plane(origin, u, v, extent, step, g):
    n = int(extent[0] * extent[1] / step**2)
    uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor(extent)
    return torch.tensor(origin) + uv[:, :1] * torch.tensor(u) + uv[:, 1:] * torch.tensor(v)


def _scene(g):
    step = 0.035
    floor = _plane((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (3.5, 1.6), step, g)
    wall = _plane((0.0, 1.6, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (3.5, 1.2), step, g)
    side = _plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.6, 1.2), step, g)
    cab_a = _box((0.6, 1.1, 0.0), (0.5, 0.5, 0.8), step, g)
    cab_b = cab_a + torch.tensor([SLIDE, 0.0, 0.0], dtype=torch.float64)
    return floor, wall, side, cab_a, cab_b


def _turn(deg: float, t) -> torch.Tensor:
    a = torch.tensor(deg).deg2rad()
    T = torch.eye(4, dtype=torch.float64)
    T[0, 0] = T[1, 1] = torch.cos(a)
    T[0, 1], T[1, 0] = -torch.sin(a), torch.sin(a)
    T[:3, 3] = torch.tensor(t, dtype=torch.float64)
    return T


def synthetic_pairs(seed: int = 0) -> list[SynthPair]:
    """The ``clean`` and the ``slid`` pair."""
    g = torch.Generator().manual_seed(seed)
    floor, wall, side, cab_a, cab_b = _scene(g)
    everything = torch.cat([floor, wall, side, cab_a, cab_b])
    src = everything[everything[:, 0] < 1.6]  # side wall, cabinet A
    tgt_world = everything[everything[:, 0] > 0.4]  # both cabinets
    T_gt = _turn(20.0, (0.3, -0.2, 0.05))  # source frame = world, target frame = T_gt world
    tgt = tgt_world @ T_gt[:3, :3].T + T_gt[:3, 3]
    pairs = []
    for name, slid in (("clean", 0), ("slid", 140)):
        n_true, n_out = 150, 1200
        a = cab_a[torch.randint(len(cab_a), (n_true + slid,), generator=g)]
        p = a.clone()
        q_world = a.clone()
        q_world[n_true:, 0] += SLIDE  # cabinet A's points matched to cabinet B's
        noise = 0.005 * torch.randn(len(a), 3, generator=g, dtype=torch.float64)
        q = (q_world + noise) @ T_gt[:3, :3].T + T_gt[:3, 3]
        p_out = src[torch.randint(len(src), (n_out,), generator=g)]
        q_out = tgt[torch.randint(len(tgt), (n_out,), generator=g)]
        p, q = torch.cat([p, p_out]), torch.cat([q, q_out])
        w = torch.rand(len(p), generator=g, dtype=torch.float64)
        pairs.append(SynthPair(name, src, tgt, src[::4], tgt[::4], (p, q, w), T_gt))
    return pairs
