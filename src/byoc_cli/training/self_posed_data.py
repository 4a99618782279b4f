"""Training views for the ``self-posed`` variant: cached frames, augmentation, correspondences.

Every frame that appears in a kept self-posed pair is back-projected once at full
resolution and thinned to the first point per ``cache_voxel`` (finer than the encoder's
voxel, so that re-voxelising after augmentation gives the density the encoder meets at test
time). A training view is then: a random subset of the cached points (density jitter), a
random rotation about a random axis through the cloud's centroid, a random scale shared by
both views of a pair, a random shift of the voxel grid, and voxelisation at the encoder's
voxel (first point per voxel). Correspondences are computed in the un-augmented frames: the
kept points of view ``j`` are moved into frame ``i`` with the pair's self-estimated
``T_i_j`` and matched to the kept points of view ``i`` that fall into the same voxel of
frame ``i``.

Shapes: a cloud is ``points (N, 3)`` float32; indices are int64.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.geometry.voxel import voxelize


class CachedFrame(NamedTuple):
    """One frame's points thinned at the cache voxel: ``points (N, 3)`` float32 metres."""

    points: torch.Tensor


class AugmentConfig(NamedTuple):
    """Augmentation ranges.

    Attributes:
        max_rotation_deg: rotation angle uniform in ``[0, max_rotation_deg)``, per view.
        scale: shared scale uniform in ``[1 - scale, 1 + scale]``.
        min_keep: each view keeps a random share of its points in ``[min_keep, 1]``.
        crop_radius: when > 0, both views keep only the points within this distance (metres)
            of one random point of view ``i`` (and of the same place in view ``j``): fewer
            points per step, the overlap kept.
        hole_prob: each view, with this probability, loses a random share of its occupied
            voxels (the encoder input of a scan sampled more sparsely than the voxel, as a
            cloud thinned after voxelisation): features that hold when one cloud is half as
            dense as the other. 0 = off (and no random number is drawn for it).
        hole_min_keep: such a view keeps a share of its voxels uniform in
            ``[hole_min_keep, 1]``.
    """

    max_rotation_deg: float = 180.0
    scale: float = 0.05
    min_keep: float = 0.7
    crop_radius: float = 0.0
    hole_prob: float = 0.0
    hole_min_keep: float = 0.25


class View(NamedTuple):
    """An augmented view.

    Attributes:
        coords: ``(M, 3)`` int64 voxel indices of the augmented cloud (encoder input).
        points: ``(M, 3)`` float32 kept points in the ORIGINAL (un-augmented) frame.
    """

    coords: torch.Tensor
    points: torch.Tensor


class PairViews(NamedTuple):
    """Two views and their correspondences ``(K, 2)`` int64: rows ``[index_i, index_j]``."""

    view_i: View
    view_j: View
    matches: torch.Tensor


PROBE_CHUNK = 32
OVERLAP_DISTANCE = 0.02


def first_point_per_voxel(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Indices (ascending) of the first point of each occupied voxel of ``points (N, 3)``."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    cells = np.floor(points / voxel_size).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    _, first = np.unique(keys, return_index=True)
    return np.sort(first)


def cache_frame(points: np.ndarray, cache_voxel: float) -> CachedFrame:
    """Thin a full-resolution frame ``points (N, 3)`` for the cache."""
    kept = points[first_point_per_voxel(points, cache_voxel)]
    return CachedFrame(torch.from_numpy(np.ascontiguousarray(kept, dtype=np.float32)))


def random_rotation(max_angle_deg: float, generator: torch.Generator) -> torch.Tensor:
    """A ``(3, 3)`` rotation: uniform axis, angle uniform in ``[0, max_angle_deg)``."""
    axis = torch.randn(3, generator=generator, dtype=torch.float64)
    axis = axis / axis.norm().clamp_min(1e-12)
    angle = math.radians(max_angle_deg) * float(torch.rand((), generator=generator))
    K = torch.zeros(3, 3, dtype=torch.float64)
    K[0, 1], K[0, 2], K[1, 2] = -axis[2], axis[1], -axis[0]
    K = K - K.T
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def augment_view(
    frame: CachedFrame,
    voxel_size: float,
    scale: float,
    config: AugmentConfig,
    generator: torch.Generator,
) -> View:
    """Subsample, rotate, scale, shift and voxelise one cached frame (see module doc)."""
    points = frame.points
    keep = config.min_keep + (1.0 - config.min_keep) * float(torch.rand((), generator=generator))
    mask = torch.rand(len(points), generator=generator) < keep
    points = points[mask]
    R = random_rotation(config.max_rotation_deg, generator).to(torch.float32)
    centre = points.mean(dim=0) if len(points) else points.new_zeros(3)
    moved = ((points - centre) @ R.T) * scale
    moved = moved + torch.rand(3, generator=generator) * voxel_size
    grid = voxelize(moved, voxel_size)
    coords, kept = grid.coords, points[grid.point_index]
    if config.hole_prob > 0 and float(torch.rand((), generator=generator)) < config.hole_prob:
        share = config.hole_min_keep + (1.0 - config.hole_min_keep) * float(
            torch.rand((), generator=generator)
        )
        cells = torch.rand(len(coords), generator=generator) < share
        coords, kept = coords[cells], kept[cells]
    return View(coords, kept)


def match_views(
    points_i: torch.Tensor, points_j: torch.Tensor, T_i_j: torch.Tensor, voxel_size: float
) -> torch.Tensor:
    """Pairs of points that fall into the same voxel of frame ``i``.

    Args:
        points_i: ``(M, 3)`` points of view ``i`` in frame ``i``.
        points_j: ``(N, 3)`` points of view ``j`` in frame ``j``.
        T_i_j: ``(4, 4)`` maps frame ``j`` into frame ``i``.
        voxel_size: the cell size.

    Returns:
        ``(K, 2)`` int64 rows ``[index into points_i, index into points_j]``, one per shared
        cell (the first point of each view in that cell).
    """
    T = T_i_j.to(torch.float32)
    moved = points_j @ T[:3, :3].T + T[:3, 3]
    cells_i = torch.floor(points_i / voxel_size).to(torch.int64)
    cells_j = torch.floor(moved / voxel_size).to(torch.int64)
    if len(cells_i) == 0 or len(cells_j) == 0:
        return torch.zeros(0, 2, dtype=torch.int64)
    low = torch.minimum(cells_i.min(0).values, cells_j.min(0).values)
    cells_i, cells_j = cells_i - low, cells_j - low
    dims = torch.maximum(cells_i.max(0).values, cells_j.max(0).values) + 1
    key_i = (cells_i[:, 0] * dims[1] + cells_i[:, 1]) * dims[2] + cells_i[:, 2]
    key_j = (cells_j[:, 0] * dims[1] + cells_j[:, 1]) * dims[2] + cells_j[:, 2]
    first_i = _first_of_key(key_i)
    first_j = _first_of_key(key_j)
    ki, kj = key_i[first_i], key_j[first_j]
    order = torch.argsort(ki)
    pos = torch.searchsorted(ki[order], kj).clamp_max(len(ki) - 1)
    hit = ki[order][pos] == kj
    return torch.stack([first_i[order][pos][hit], first_j[hit]], dim=1)


def _first_of_key(keys: torch.Tensor) -> torch.Tensor:
    """Index of the first occurrence of each distinct key (ascending keys order)."""
    uniq, inverse = torch.unique(keys, return_inverse=True)
    first = torch.full((len(uniq),), len(keys), dtype=torch.int64)
    first.scatter_reduce_(0, inverse, torch.arange(len(keys)), reduce="amin")
    return first


def make_pair_views(
    frame_i: CachedFrame,
    frame_j: CachedFrame,
    T_i_j: torch.Tensor,
    voxel_size: float,
    config: AugmentConfig,
    generator: torch.Generator,
) -> PairViews:
    """Two augmented views of a self-posed pair and their correspondences."""
    if config.crop_radius > 0:
        frame_i, frame_j = crop_pair(frame_i, frame_j, T_i_j, config.crop_radius, generator)
    scale = 1.0 + config.scale * (2.0 * float(torch.rand((), generator=generator)) - 1.0)
    view_i = augment_view(frame_i, voxel_size, scale, config, generator)
    view_j = augment_view(frame_j, voxel_size, scale, config, generator)
    matches = match_views(view_i.points, view_j.points, T_i_j, voxel_size)
    return PairViews(view_i, view_j, matches)


def crop_pair(
    frame_i: CachedFrame,
    frame_j: CachedFrame,
    T_i_j: torch.Tensor,
    radius: float,
    generator: torch.Generator,
) -> tuple[CachedFrame, CachedFrame]:
    """Both frames cut to a ball of ``radius`` around one random point of frame ``i``.

    The centre is drawn among the points of ``i`` that land next to a point of ``j``
    (within 2 cm under ``T_i_j``) when there are any, so that the crops overlap: uniformly
    among the near ones of up to 256 random probes, else among all probes. The probes are
    tested in chunks of 32 (the first chunk with a near probe decides, which draws from the
    same distribution as testing all 256 at once at a fraction of the cost), and in frame
    ``j``: the ball is cut there around the centre moved by ``T_i_j``'s inverse, so frame
    ``j``'s points are never transformed.
    """
    points_i, points_j = frame_i.points, frame_j.points
    T = T_i_j.to(torch.float32)
    R, t = T[:3, :3], T[:3, 3]
    probe = torch.randint(len(points_i), (min(256, len(points_i)),), generator=generator)
    candidates = probe
    for chunk in torch.split(probe, PROBE_CHUNK):
        near = _near_any((points_i[chunk] - t) @ R, points_j, OVERLAP_DISTANCE)
        if bool(near.any()):
            candidates = chunk[near]
            break
    centre = points_i[candidates[torch.randint(len(candidates), (1,), generator=generator)]]
    centre_j = (centre - t) @ R  # the same point in frame j: R^T (c - t)
    keep_i = ((points_i - centre) ** 2).sum(dim=1) < radius**2
    keep_j = ((points_j - centre_j) ** 2).sum(dim=1) < radius**2
    return CachedFrame(points_i[keep_i]), CachedFrame(points_j[keep_j])


def _near_any(queries: torch.Tensor, points: torch.Tensor, distance: float) -> torch.Tensor:
    """``(Q,)`` bool: whether each of ``queries (Q, 3)`` has a point of ``points (N, 3)``
    closer than ``distance`` (all False when ``points`` is empty)."""
    if len(points) == 0:
        return torch.zeros(len(queries), dtype=torch.bool)
    return torch.cdist(queries, points).min(dim=1).values < distance
