"""Pairs of many clouds (``register-scans``, ``odometry``): the one refinement
(:func:`~byoc_cli.pipeline.refine.refine_multiscale`) at an ICP voxel, with the fit's fitness,
RMSE and information matrix for a pose graph."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from byoc_cli.geometry.neighbors import nearest_candidates, nearest_of
from byoc_cli.pipeline.refine import refine_multiscale
from byoc_cli.pipeline.refine_levels import LEVELS, RefineCloud

#: the finest ICP voxel ``w`` of ``register-scans`` and ``odometry`` as a multiple of the
#: refinement's voxel ``v``: the finest level (``0.4v``); the levels are then
#: ``(2.5w, 5w)``, ``(1.25w, 2.5w)``, ``(w, 1.5w)``
FINE_VOXEL = LEVELS[-1][0]
#: the finest correspondence distance as a multiple of the finest ICP voxel (1.5): the
#: distance of the fitness, the RMSE, the information matrix and the pose graph
FINE_DISTANCE = LEVELS[-1][1] / LEVELS[-1][0]
#: fewest points per level for a pair's refinement to mean anything (normals, point-to-plane)
MIN_PAIR_POINTS = 10


class PairFit:
    """:func:`refine_pair`'s result.

    Attributes:
        T_tgt_src: ``(4, 4)`` float64 array.
        fitness: share of the source's points with a target point within the finest
            distance (``FINE_DISTANCE`` ICP voxels).
        rmse: root mean square distance of those points to their nearest target point
            (metres; nan when no level ran).
        information: ``(6, 6)`` information matrix of the finest correspondences (rotation
            first, then translation: Open3D's order, that of its pose graph); given, or
            measured on first read by a callable (only the pairs that become edges of a
            pose graph need it).
    """

    __slots__ = ("T_tgt_src", "_information", "fitness", "rmse")

    def __init__(
        self,
        T_tgt_src: np.ndarray,
        fitness: float,
        rmse: float,
        information: np.ndarray | Callable[[], np.ndarray],
    ) -> None:
        self.T_tgt_src, self.fitness, self.rmse = T_tgt_src, fitness, rmse
        self._information = information

    @property
    def information(self) -> np.ndarray:
        if callable(self._information):
            self._information = self._information()
        return self._information

    def __repr__(self) -> str:
        return f"PairFit(fitness={self.fitness:.4f}, rmse={self.rmse:.5f})"


def pair_cloud(points: torch.Tensor | np.ndarray, icp_voxel: float) -> RefineCloud:
    """``points (N, 3)`` prepared for :func:`refine_pair` with the finest ICP voxel
    ``icp_voxel`` (levels built on use)."""
    return RefineCloud(points, icp_voxel / FINE_VOXEL, pyramid=True)


def icp_voxel(cloud: RefineCloud) -> float:
    """The finest ICP voxel of a :func:`pair_cloud`."""
    return cloud.voxel_size * FINE_VOXEL


def enough_points(cloud: RefineCloud, min_points: int = MIN_PAIR_POINTS) -> bool:
    """True when every level of ``cloud`` keeps at least ``min_points`` points."""
    return all(len(cloud.source(level)) >= min_points for level in range(len(cloud.levels)))


def refine_pair(src: RefineCloud, tgt: RefineCloud, T_init: np.ndarray, parallel=None) -> PairFit:
    """:func:`refine_multiscale` of ``src`` onto ``tgt`` (two :func:`pair_cloud` of one ICP
    voxel) from ``T_init (4, 4)``, with the fit's fitness, RMSE and information matrix
    (measured when first read)."""
    voxel = src.voxel_size
    start = torch.from_numpy(np.asarray(T_init, dtype=np.float64))
    out = refine_multiscale(src, tgt, start, voxel, parallel=parallel)
    T = out.T_tgt_src

    def information() -> np.ndarray:
        return information_matrix(src, tgt, T, LEVELS[-1][1] * voxel)

    return PairFit(T.numpy().copy(), out.fitness, out.rmse * voxel, information)


def information_matrix(
    src: RefineCloud, tgt: RefineCloud, T_tgt_src: torch.Tensor, distance: float
) -> np.ndarray:
    """The ``(6, 6)`` information matrix of ``T_tgt_src`` at the finest level: over the
    source points with a target point within ``distance`` (metres), the sum of
    ``J^T J``, ``J = [-[t]x | I]`` at that target point ``t`` (the matrix Open3D's pose graph
    takes, in its order: rotation, then translation)."""
    level = len(src.levels) - 1
    q, _, index = tgt.target(level)
    p = src.source(level)
    T = T_tgt_src.to(torch.float64)
    moved = p @ T[:3, :3].T + T[:3, 3]
    if len(moved) == 0 or len(q) == 0:
        return np.zeros((6, 6))
    reach = math.ceil(distance / index.size)  # every target point within the distance
    near = nearest_of(index, moved, nearest_candidates(index, moved, 1, reach))
    ok = (near.index >= 0) & (near.distance2 <= distance**2)
    t = q[near.index[ok]].to(torch.float64)  # (K, 3)
    x, y, z = t.unbind(1)
    zero, one = torch.zeros_like(x), torch.ones_like(x)
    J = torch.stack(
        [
            torch.stack([zero, z, -y, one, zero, zero], 1),
            torch.stack([-z, zero, x, zero, one, zero], 1),
            torch.stack([y, -x, zero, zero, zero, one], 1),
        ],
        1,
    )  # (K, 3, 6)
    return torch.einsum("kai,kaj->ij", J, J).numpy()


#: restarts of the refinement, the check of the basin a result sits in: the result turned by
#: +-RESTART_DEG about each axis through the source's centroid (6 starts), each refined on at
#: most RESTART_POINTS source points per level
