"""The multiscale refinement's pyramid: a cloud as voxel averages, normals and a search index
per level, built once on first use (:class:`RefineCloud`).

Three levels of voxel size and correspondence distance, in multiples of the feature voxel
``v``: ``(v, 2v)``, ``(v/2, v)``, ``(0.4v, 0.6v)``; voxel averages, normals and the nearest-point
index come from voxel grids (:mod:`byoc_cli.geometry.neighbors`; one point per cell).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence

import numpy as np
import torch

from byoc_cli.geometry.neighbors import CellIndex, voxel_average, voxel_means
from byoc_cli.geometry.normals import surface_normals

#: (voxel, correspondence distance) per level, in multiples of the feature voxel size
LEVELS = ((1.0, 2.0), (0.5, 1.0), (0.4, 0.6))
#: reach of the nearest-point search per level, in level voxels (cells of the target's
#: voxel averages, one point each): the first level searches its whole correspondence
#: distance (2 voxels; it meets the feature estimate's error), the finer ones, which start
#: where the coarser left off, one voxel (27 cells instead of 125)
SEARCH_REACH = (2, 1, 1)
#: normals from the cells of edge NORMAL_CELL * radius around a point, radius
#: max(2 level voxels, NORMAL_RADIUS v)
NORMAL_RADIUS = 1.2
NORMAL_CELL = 0.5
#: source points per level at most (an even stride through the voxel averages)
MAX_SOURCE_POINTS = 20_000


def _level_geometry(voxel_size: float) -> list[tuple[float, float, float]]:
    """``(voxel, correspondence distance, normal radius)`` per level, in metres."""
    out = []
    for voxel_factor, dist_factor in LEVELS:
        size = voxel_factor * voxel_size
        out.append((size, dist_factor * voxel_size, max(2.0 * size, NORMAL_RADIUS * voxel_size)))
    return out


class RefineCloud:
    """A cloud prepared for :func:`refine_multiscale`, level by level, on first use.

    As a source a level is its voxel averages (every s-th one, at most
    ``MAX_SOURCE_POINTS``); as a target, its voxel averages, their unit normals and a cell
    index over them. Each is built once and kept: ``register-batch`` refines every
    fragment in several pairs. Safe to share between threads (a level is built once).

    Args:
        points: ``(N, 3)`` points (metres), a tensor or an array.
        voxel_size: the feature voxel ``v`` the levels scale with.
        pyramid: average the points at the finest level only and each coarser level from
            the finer level's averages, weighted by their point counts (one pass over the
            points instead of one per level; a point near a coarse cell's border may go
            with its fine cell's average to the cell next door): for the many
            full-resolution clouds of ``odometry`` and ``register-scans``
            (:func:`pair_cloud`).
    """

    def __init__(
        self, points: torch.Tensor | np.ndarray, voxel_size: float, pyramid: bool = False
    ) -> None:
        if not isinstance(points, torch.Tensor):
            points = torch.from_numpy(np.asarray(points))
        self.points = points.detach().to(device="cpu", dtype=torch.float64)
        self.voxel_size = float(voxel_size)
        self.levels = _level_geometry(self.voxel_size)
        self.pyramid = pyramid
        self._weights: dict[int, torch.Tensor] = {}  # pyramid: points per average
        self._averages: dict[int, torch.Tensor] = {}
        self._sources: dict[tuple[int, int], torch.Tensor] = {}
        self._targets: dict[int, tuple[torch.Tensor, torch.Tensor, CellIndex]] = {}
        # one lock per level: levels are built side by side, each once
        self._locks = [threading.RLock() for _ in self.levels]

    def average(self, level: int) -> torch.Tensor:
        """``(M, 3)`` voxel averages of the points at ``level``'s voxel."""
        with self._locks[level]:
            if level not in self._averages:
                size = self.levels[level][0]
                if not self.pyramid:
                    self._averages[level] = voxel_average(self.points, size)
                elif level == len(self.levels) - 1:
                    self._averages[level], self._weights[level] = voxel_means(self.points, size)
                else:  # the finer level first (its lock after this one's: no cycle)
                    finer = self.average(level + 1)
                    means = voxel_means(finer, size, self._weights[level + 1])
                    self._averages[level], self._weights[level] = means
            return self._averages[level]

    def source(self, level: int, max_points: int = MAX_SOURCE_POINTS) -> torch.Tensor:
        """``(K, 3)`` source points of ``level``, ``K <= max_points`` (an even stride)."""
        with self._locks[level]:
            if (level, max_points) not in self._sources:
                p = self.average(level)
                self._sources[level, max_points] = p[:: max(1, -(-len(p) // max_points))]
            return self._sources[level, max_points]

    def oriented_source(
        self, level: int, max_points: int = MAX_SOURCE_POINTS
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`source` of ``level`` ``(K, 3)`` and the ``(K, 3)`` unit normals of those
        points (the ones the level has as a target)."""
        p = self.source(level, max_points)
        n = self.target(level)[1]
        return p, n[:: max(1, -(-len(n) // max_points))]

    def target(self, level: int) -> tuple[torch.Tensor, torch.Tensor, CellIndex]:
        """``(M, 3)`` target points of ``level``, their ``(M, 3)`` normals, and a
        :class:`CellIndex` over them at the level's voxel."""
        with self._locks[level]:
            if level not in self._targets:
                size, _, radius = self.levels[level]
                q = self.average(level)
                n = surface_normals(q, NORMAL_CELL * radius)
                self._targets[level] = (q, n, CellIndex(q, size, SEARCH_REACH[level]))
            return self._targets[level]

    def prepare(
        self, source: bool = True, target: bool = True, levels: Sequence[int] | None = None
    ) -> RefineCloud:
        """Build ``levels`` (default: all) now, as a source, a target or both; ``self``."""
        for level in range(len(self.levels)) if levels is None else levels:
            if source:
                self.source(level)
            if target:
                self.target(level)
        return self

    def drop_points(self) -> RefineCloud:
        """Build every level, then keep the finest level's voxel averages in place of the
        full-resolution points (a cloud kept for later pairs only: the past keyframes of
        ``odometry --pose-graph``); the levels, and so every refinement, stay the same;
        ``self``."""
        self.prepare()
        self.points = self.average(len(self.levels) - 1)
        return self


def _prepared(points, voxel_size: float) -> RefineCloud:
    if isinstance(points, RefineCloud):
        if not math.isclose(points.voxel_size, voxel_size, rel_tol=1e-9):
            raise ValueError(
                f"RefineCloud prepared for voxel {points.voxel_size:g} m, "
                f"refining at {voxel_size:g} m"
            )
        return points
    return RefineCloud(points, voxel_size)
