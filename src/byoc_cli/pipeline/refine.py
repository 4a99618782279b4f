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

import math
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


def _level_geometry(voxel_size: float) -> list[tuple[float, float, float]]:
    """``(voxel, correspondence distance, normal radius)`` per level, in metres."""
    out = []
    for voxel_factor, dist_factor in LEVELS:
        size = voxel_factor * voxel_size
        out.append((size, dist_factor * voxel_size, max(2.0 * size, NORMAL_RADIUS * voxel_size)))
    return out


class RefineCloud:
    """A cloud prepared for :func:`refine_multiscale`, level by level, on first use.

    As a source a level is its voxel centres (every s-th one, at most ``MAX_SOURCE_POINTS``);
    as a target, its voxel centres, their unit normals and a nearest-neighbour index. Each is
    built once and kept: ``register-batch`` refines every fragment in several pairs.

    Args:
        points: ``(N, 3)`` points (metres), a tensor or an array.
        voxel_size: the feature voxel ``v`` the levels scale with.
    """

    def __init__(self, points: torch.Tensor | np.ndarray, voxel_size: float) -> None:
        if isinstance(points, torch.Tensor):
            points = points.detach().double().cpu().numpy()
        self.points = np.asarray(points, dtype=np.float64)
        self.voxel_size = float(voxel_size)
        self.levels = _level_geometry(self.voxel_size)
        self._sources: dict[int, np.ndarray] = {}
        self._targets: dict[int, tuple[np.ndarray, np.ndarray, object]] = {}

    def source(self, level: int) -> np.ndarray:
        """``(K, 3)`` source points of ``level``."""
        if level not in self._sources:
            p = np.asarray(_downsample(_open3d(), self.points, self.levels[level][0]).points)
            self._sources[level] = p[:: max(1, -(-len(p) // MAX_SOURCE_POINTS))]
        return self._sources[level]

    def target(self, level: int) -> tuple[np.ndarray, np.ndarray, object]:
        """``(M, 3)`` target points of ``level``, their ``(M, 3)`` normals, and an Open3D
        nearest-neighbour search over them (None when there are too few points)."""
        if level not in self._targets:
            o3d = _open3d()
            size, _, radius = self.levels[level]
            cloud = _downsample(o3d, self.points, size)
            cloud.estimate_normals(
                o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=NORMAL_MAX_NN)
            )
            q, n = np.asarray(cloud.points), np.asarray(cloud.normals)
            search = None
            if len(q) >= MIN_CORRESPONDENCES:
                search = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(q.astype(np.float32)))
                search.knn_index()
            self._targets[level] = (q, n, search)
        return self._targets[level]


def refine_multiscale(
    points_src: torch.Tensor | RefineCloud,
    points_tgt: torch.Tensor | RefineCloud,
    T_init: torch.Tensor,
    voxel_size: float,
    degeneracy: float = DEGENERACY,
    sliding: float = SLIDING,
) -> Refinement:
    """Refine ``T_init`` by coarse-to-fine point-to-plane ICP.

    Args:
        points_src: ``(N, 3)`` source points (full resolution, metres), or a
            :class:`RefineCloud` of them (prepared levels are reused).
        points_tgt: ``(M, 3)`` target points, or a :class:`RefineCloud`.
        T_init: ``(4, 4)`` initial ``T_tgt_src`` (from feature matching).
        voxel_size: the feature voxel ``v``; the levels scale with it.
        degeneracy, sliding: see :func:`point_to_plane_step`; both 0 = plain
            point-to-plane ICP.

    Returns:
        :class:`Refinement`; ``T_init`` itself where a level has fewer than
        ``MIN_CORRESPONDENCES`` correspondences.

    Raises:
        DependencyError: open3d cannot be imported (the message names ``--refine none``).
        ValueError: a :class:`RefineCloud` was prepared for another voxel size.
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


def _prepared(points, voxel_size: float) -> RefineCloud:
    if isinstance(points, RefineCloud):
        if not math.isclose(points.voxel_size, voxel_size, rel_tol=1e-9):
            raise ValueError(
                f"RefineCloud prepared for voxel {points.voxel_size:g} m, "
                f"refining at {voxel_size:g} m"
            )
        return points
    return RefineCloud(points, voxel_size)


def _refine(points_src, points_tgt, T_init, voxel_size, degeneracy, sliding) -> Refinement:
    src, tgt = _prepared(points_src, voxel_size), _prepared(points_tgt, voxel_size)
    o3d = _open3d()
    T = T_init.detach().double().cpu().numpy().copy()
    rank, fitness = 0, 0.0
    for level, (_, dist, _) in enumerate(src.levels):
        p = src.source(level)
        q, n, search = tgt.target(level)
        if len(p) < MIN_CORRESPONDENCES or search is None:
            break
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
