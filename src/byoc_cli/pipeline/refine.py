"""Coarse-to-fine point-to-plane ICP that holds degenerate directions (Open3D, lazily).

The refinement behind ``--refine multiscale`` (the default of learned features): three
levels of voxel size and correspondence distance, in multiples of the feature voxel ``v``:
``(v, 2v)``, ``(v/2, v)``, ``(0.4v, 0.6v)``, each up to 30 Gauss-Newton steps of
:func:`byoc_cli.fitting.point_to_plane.point_to_plane_step`. Open3D does the voxel grid,
the normals and the nearest-neighbour search; the step is ours, because Open3D's ICP
slides along planes (``point_to_plane.py`` says why and what is held).

It runs on the full-resolution input points: the kept points of the feature voxel are too
coarse for the finest level (README, "Measured levers").
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.errors import DependencyError, require_open3d
from byoc_cli.fitting.point_to_plane import DEGENERACY, SLIDING, point_to_plane_step

#: (voxel, correspondence distance) per level, in multiples of the feature voxel size
LEVELS = ((1.0, 2.0), (0.5, 1.0), (0.4, 0.6))
#: Gauss-Newton steps per level at most
ITERATIONS = 30
#: normals from at most this many neighbours within max(2 level voxels, NORMAL_RADIUS v)
NORMAL_MAX_NN = 30
NORMAL_RADIUS = 1.2
#: a level stops when a step moves less than this (radians, and multiples of v)
TOLERANCE = 4e-4
#: source points per level at most (an even stride through the voxel centres)
MAX_SOURCE_POINTS = 20_000
#: fewest correspondences for a step (fewer: the level is skipped)
MIN_CORRESPONDENCES = 6


class Refinement(NamedTuple):
    """Outcome of :func:`refine_multiscale`.

    Attributes:
        T_tgt_src: ``(4, 4)`` float64.
        rank: directions the last step of the finest level moved (6 = none held).
        fitness: share of source points with a target point within the finest distance.
    """

    T_tgt_src: torch.Tensor
    rank: int
    fitness: float


def _downsample(o3d, points: np.ndarray, size: float):
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(size)


def _source_level(o3d, points: np.ndarray, size: float) -> np.ndarray:
    """``(K, 3)`` voxel centres, every s-th one so that at most MAX_SOURCE_POINTS remain."""
    p = np.asarray(_downsample(o3d, points, size).points)
    return p[:: max(1, -(-len(p) // MAX_SOURCE_POINTS))]


def _target_level(o3d, points: np.ndarray, size: float, radius: float):
    """Voxel centres ``(M, 3)`` and their unit normals ``(M, 3)``."""
    cloud = _downsample(o3d, points, size)
    cloud.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=NORMAL_MAX_NN)
    )
    return np.asarray(cloud.points), np.asarray(cloud.normals)


def refine_multiscale(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    T_init: torch.Tensor,
    voxel_size: float,
    degeneracy: float = DEGENERACY,
    sliding: float = SLIDING,
) -> Refinement:
    """Refine ``T_init`` by coarse-to-fine point-to-plane ICP.

    Args:
        points_src: ``(N, 3)`` source points (full resolution, metres).
        points_tgt: ``(M, 3)`` target points.
        T_init: ``(4, 4)`` initial ``T_tgt_src`` (from feature matching).
        voxel_size: the feature voxel ``v``; the levels scale with it.
        degeneracy, sliding: see :func:`point_to_plane_step`; both 0 = plain
            point-to-plane ICP.

    Returns:
        :class:`Refinement`; ``T_init`` itself where a level has fewer than
        ``MIN_CORRESPONDENCES`` correspondences.

    Raises:
        DependencyError: open3d cannot be imported (the message names ``--refine none``).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: extra threads only wait on each other (10x slower)
    try:
        return _refine(points_src, points_tgt, T_init, voxel_size, degeneracy, sliding)
    finally:
        torch.set_num_threads(threads)


def _open3d():
    """open3d, or a :class:`DependencyError` that says how to register without it."""
    try:
        return require_open3d()
    except DependencyError as exc:
        raise DependencyError(
            f"multiscale refinement: {exc} (or register without it: --refine none)"
        ) from exc


def _refine(points_src, points_tgt, T_init, voxel_size, degeneracy, sliding) -> Refinement:
    o3d = _open3d()
    src = points_src.detach().double().cpu().numpy()
    tgt = points_tgt.detach().double().cpu().numpy()
    T = T_init.detach().double().cpu().numpy().copy()
    rank, fitness = 0, 0.0
    for voxel_factor, dist_factor in LEVELS:
        size, dist = voxel_factor * voxel_size, dist_factor * voxel_size
        radius = max(2.0 * size, NORMAL_RADIUS * voxel_size)
        p = _source_level(o3d, src, size)
        q, n = _target_level(o3d, tgt, size, radius)
        if len(p) < MIN_CORRESPONDENCES or len(q) < MIN_CORRESPONDENCES:
            break
        search = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(q.astype(np.float32)))
        search.knn_index()
        for _ in range(ITERATIONS):
            moved = p @ T[:3, :3].T + T[:3, 3]
            idx, d2 = search.knn_search(o3d.core.Tensor(moved.astype(np.float32)), 1)
            ok = d2.numpy().ravel() <= dist**2
            fitness = float(ok.mean())
            if ok.sum() < MIN_CORRESPONDENCES:
                break
            j = idx.numpy().ravel()[ok].astype(np.int64)
            step = point_to_plane_step(
                torch.from_numpy(moved[ok]),
                torch.from_numpy(q[j]),
                torch.from_numpy(n[j]),
                degeneracy=degeneracy,
                sliding=sliding,
            )
            dT = step.T.numpy()
            T = dT @ T
            rank = step.rank
            angle = np.arccos(np.clip((np.trace(dT[:3, :3]) - 1) / 2, -1.0, 1.0))
            if angle < TOLERANCE and np.linalg.norm(dT[:3, 3]) < TOLERANCE * voxel_size:
                break
    return Refinement(torch.from_numpy(T), rank, fitness)
