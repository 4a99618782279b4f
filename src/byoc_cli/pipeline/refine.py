"""Coarse-to-fine point-to-plane ICP that holds degenerate directions, in plain PyTorch.

The refinement behind ``--refine multiscale`` (the default of learned features): three
levels of voxel size and correspondence distance, in multiples of the feature voxel ``v``:
``(v, 2v)``, ``(v/2, v)``, ``(0.4v, 0.6v)``, each up to 30 Gauss-Newton steps of
:func:`byoc_cli.fitting.point_to_plane.point_to_plane_step` (Open3D's ICP slides along
planes: ``point_to_plane.py`` says why and what is held). Voxel averages, normals and
nearest points come from voxel grids (:mod:`byoc_cli.geometry.neighbors`): no k-d tree and
no open3d, whose import alone took longer than the whole refinement does now.

Correspondences: each source point's 8 nearest target points among the 27 cells of the
level's voxel around it are gathered once, and again only after a point has moved more
than half a voxel since; every step takes the nearest of those (within the level's
correspondence distance).

It runs on the full-resolution input points: the kept points of the feature voxel are too
coarse for the finest level (README, "Measured levers").
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.fitting.point_to_plane import (
    DEGENERACY,
    SLIDING,
    PlaneStep,
    point_to_plane_step,
    point_to_plane_steps,
)
from byoc_cli.geometry.neighbors import (
    CellIndex,
    Nearest,
    candidate_coordinates,
    nearest_candidates,
    nearest_of,
    surface_normals,
    voxel_average,
    voxel_means,
)

#: (voxel, correspondence distance) per level, in multiples of the feature voxel size
LEVELS = ((1.0, 2.0), (0.5, 1.0), (0.4, 0.6))
#: reach of the nearest-point search per level, in level voxels (cells of the target's
#: voxel averages, one point each): the first level searches its whole correspondence
#: distance (2 voxels; it meets the feature estimate's error), the finer ones, which start
#: where the coarser left off, one voxel (27 cells instead of 125)
SEARCH_REACH = (2, 1, 1)
#: Gauss-Newton steps per level at most
ITERATIONS = 30
#: normals from the cells of edge NORMAL_CELL * radius around a point, radius
#: max(2 level voxels, NORMAL_RADIUS v)
NORMAL_RADIUS = 1.2
NORMAL_CELL = 0.5
#: a level stops when a step moves less than this (radians, and multiples of v)
TOLERANCE = 4e-4
#: source points per level at most (an even stride through the voxel averages)
MAX_SOURCE_POINTS = 20_000
#: fewest correspondences for a step (fewer: the level is skipped)
MIN_CORRESPONDENCES = 6
#: nearest target points kept per source point between searches
CANDIDATES = 8
#: a new search once a source point has moved this many level voxels since the last
RESEARCH = 1.0


class Refinement(NamedTuple):
    """Outcome of :func:`refine_multiscale`.

    Attributes:
        T_tgt_src: ``(4, 4)`` float64.
        rank: directions the last step of the finest level moved (6 = none held).
        fitness: share of source points with a target point within the finest distance.
        rmse: root mean square distance of those points to their nearest target point, in
            multiples of the feature voxel (nan when no level ran).
        conditioning: smallest eigenvalue of the last step's normal equations over the
            largest (0 when no step ran): near 0, the geometry leaves a direction free.
    """

    T_tgt_src: torch.Tensor
    rank: int
    fitness: float
    rmse: float = float("nan")
    conditioning: float = 0.0


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


def refine_multiscale(
    points_src: torch.Tensor | RefineCloud,
    points_tgt: torch.Tensor | RefineCloud,
    T_init: torch.Tensor,
    voxel_size: float,
    degeneracy: float = DEGENERACY,
    sliding: float = SLIDING,
    parallel: Callable[[Sequence[Callable[[], torch.Tensor]]], list] | None = None,
    max_source_points: int = MAX_SOURCE_POINTS,
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
        parallel: runs independent calls (results in order), e.g. side by side on two
            threads (:func:`byoc_cli.threads.side_by_side`): the nearest-point searches of
            the two halves of the source points. None: in turn. The result is the same.
        max_source_points: source points per level at most.

    Returns:
        :class:`Refinement`; ``T_init`` itself where a level has fewer than
        ``MIN_CORRESPONDENCES`` correspondences.

    Raises:
        ValueError: a :class:`RefineCloud` was prepared for another voxel size.
    """
    src, tgt = _prepared(points_src, voxel_size), _prepared(points_tgt, voxel_size)
    T = T_init.detach().to(device="cpu", dtype=torch.float64).clone()
    rank, fitness, rmse, conditioning = 0, 0.0, float("nan"), 0.0
    for level, (size, dist, _) in enumerate(src.levels):
        p = src.source(level, max_source_points)  # levels, normals and searches: all threads
        q, n, index = tgt.target(level)
        if len(p) < MIN_CORRESPONDENCES or len(q) < MIN_CORRESPONDENCES:
            break
        anchor, candidates = None, None
        for _ in range(ITERATIONS):
            moved = p @ T[:3, :3].T + T[:3, 3]
            if anchor is None or float((moved - anchor).abs().max()) > RESEARCH * size:
                candidates = _search(index, moved, SEARCH_REACH[level], parallel)
                coordinates = candidate_coordinates(index, candidates)
                anchor = moved
            near = nearest_of(index, moved, candidates, coordinates)
            fitness, level_rmse, step = _meet(
                moved, near, (q, n), dist, voxel_size, (degeneracy, sliding)
            )
            if step is None:
                break
            rmse = level_rmse
            T = step.T @ T
            rank, conditioning = step.rank, float(step.eigenvalues[0])
            dR = step.T[:3, :3]
            angle = math.acos(max(-1.0, min(1.0, (float(torch.trace(dR)) - 1) / 2)))
            if angle < TOLERANCE and float(step.T[:3, 3].norm()) < TOLERANCE * voxel_size:
                break
    return Refinement(T, rank, fitness, rmse, conditioning)


def measure_fit(
    points_src: torch.Tensor | RefineCloud,
    points_tgt: torch.Tensor | RefineCloud,
    T: torch.Tensor,
    voxel_size: float,
) -> Refinement:
    """How well ``T (4, 4)`` fits, measured as :func:`refine_multiscale` measures its own
    result, without moving it: the finest level's fitness and residual, and the rank and
    conditioning of its normal equations at ``T``. The confidence of a result that is not
    refined reads these (a transform is judged by how its clouds meet, whether or not it
    was refined).

    Args: as :func:`refine_multiscale`.

    Returns:
        :class:`Refinement` with ``T_tgt_src = T``; fitness 0 and rank 0 where fewer than
        ``MIN_CORRESPONDENCES`` points meet.
    """
    src, tgt = _prepared(points_src, voxel_size), _prepared(points_tgt, voxel_size)
    T = T.detach().to(device="cpu", dtype=torch.float64).clone()
    level = len(src.levels) - 1
    _, dist, _ = src.levels[level]
    p = src.source(level)
    q, n, index = tgt.target(level)
    if len(p) < MIN_CORRESPONDENCES or len(q) < MIN_CORRESPONDENCES:
        return Refinement(T, 0, 0.0)
    moved = p @ T[:3, :3].T + T[:3, 3]
    near = nearest_of(index, moved, _search(index, moved, SEARCH_REACH[level], None))
    fitness, rmse, step = _meet(moved, near, (q, n), dist, voxel_size)
    if step is None:
        return Refinement(T, 0, fitness)
    return Refinement(T, step.rank, fitness, rmse, float(step.eigenvalues[0]))


def _meet(
    moved: torch.Tensor,
    near: Nearest,
    planes: tuple[torch.Tensor, torch.Tensor],
    dist: float,
    voxel_size: float,
    held: tuple[float, float] = (DEGENERACY, SLIDING),
) -> tuple[float, float, PlaneStep | None]:
    """How source points ``moved (K, 3)`` meet their ``near`` target points: the share
    within ``dist`` (metres; the fitness), their RMS distance in feature voxels, and
    the point-to-plane step onto the target ``planes`` (points ``(M, 3)``, normals
    ``(M, 3)``) with ``held = (degeneracy, sliding)``; residual nan and no step where fewer
    than ``MIN_CORRESPONDENCES`` meet."""
    ok = near.distance2 <= dist**2
    fitness = float(ok.double().mean())
    if int(ok.sum()) < MIN_CORRESPONDENCES:
        return fitness, float("nan"), None
    rmse = math.sqrt(float(near.distance2[ok].double().mean())) / voxel_size
    j = near.index[ok]
    q, n = planes
    # tiny tensors: extra threads only wait on each other (10x slower)
    with _threads(1):
        step = point_to_plane_step(moved[ok], q[j], n[j], degeneracy=held[0], sliding=held[1])
    return fitness, rmse, step


#: fewest source points whose search is split in two for ``parallel``
SPLIT_SEARCH = 4096


def _search(index: CellIndex, queries: torch.Tensor, reach: int, parallel) -> torch.Tensor:
    """:func:`nearest_candidates` of ``queries (Q, 3)``, by halves through ``parallel`` (each
    row's search is its own: the halves give the rows of the whole)."""
    if parallel is None or len(queries) < SPLIT_SEARCH:
        return nearest_candidates(index, queries, CANDIDATES, reach)
    half = len(queries) // 2
    parts = parallel(
        [
            lambda: nearest_candidates(index, queries[:half], CANDIDATES, reach),
            lambda: nearest_candidates(index, queries[half:], CANDIDATES, reach),
        ]
    )
    return torch.cat(parts)


def _prepared(points, voxel_size: float) -> RefineCloud:
    if isinstance(points, RefineCloud):
        if not math.isclose(points.voxel_size, voxel_size, rel_tol=1e-9):
            raise ValueError(
                f"RefineCloud prepared for voxel {points.voxel_size:g} m, "
                f"refining at {voxel_size:g} m"
            )
        return points
    return RefineCloud(points, voxel_size)


@contextlib.contextmanager
def _threads(count: int) -> Iterator[None]:
    """Run the block with ``count`` torch threads."""
    before = torch.get_num_threads()
    if before == count:  # (a worker of byoc_cli.threads.worker_pool runs one already)
        yield
        return
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


# ------------------------------------------------------------------ pairs of many clouds

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
RESTART_DEG = 8.0
RESTART_POINTS = 2000
#: two refined ends closer than this (degrees, and multiples of the feature voxel) are one place
SAME_DEG = 1.0
SAME_VOXELS = 1.0


class Restarts(NamedTuple):
    """Outcome of :func:`restart_refinement`.

    Attributes:
        ends: ``(S, 4, 4)`` float64: where the refinement ends from each start; start 0 is
            the result itself.
        fitness: ``(S,)`` float64 fitness of each end (the same reduced refinement for all).
        voxel_size: the feature voxel the places are compared at.
    """

    ends: torch.Tensor
    fitness: torch.Tensor
    voxel_size: float

    def same_place(self, i: int) -> torch.Tensor:
        """``(S,)`` bool: the ends within ``SAME_DEG`` and ``SAME_VOXELS`` of end ``i``."""
        D = torch.linalg.inv(self.ends[i]) @ self.ends
        cos = ((D[:, :3, :3].diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
        angle = torch.rad2deg(torch.arccos(cos))
        shift = torch.linalg.vector_norm(D[:, :3, 3], dim=-1) / self.voxel_size
        return (angle < SAME_DEG) & (shift < SAME_VOXELS)

    def best(self) -> int:
        """The end of highest fitness (the first on ties)."""
        return int(torch.argmax(self.fitness))

    def gain(self, i: int) -> float:
        """Highest fitness of the ends elsewhere than end ``i`` minus end ``i``'s (-1: every
        end is in its place)."""
        elsewhere = ~self.same_place(i)
        if not bool(elsewhere.any()):
            return -1.0
        return float(self.fitness[elsewhere].max() - self.fitness[i])

    def returned(self, i: int) -> float:
        """Share of the restarts (starts 1 on) that end in end ``i``'s place."""
        return float(self.same_place(i)[1:].double().mean()) if len(self.ends) > 1 else 1.0


def restart_starts(T: torch.Tensor, centroid: torch.Tensor) -> torch.Tensor:
    """``(7, 4, 4)`` starts: ``T (4, 4)`` itself, then turned by +-``RESTART_DEG`` about each
    axis through the source point ``centroid (3,)``."""
    starts = [T]
    for axis in range(3):
        for sign in (-1.0, 1.0):
            angle = math.radians(sign * RESTART_DEG)
            i, j = [(1, 2), (0, 2), (0, 1)][axis]
            M = torch.eye(4, dtype=torch.float64)
            M[i, i] = M[j, j] = math.cos(angle)
            M[i, j], M[j, i] = -math.sin(angle), math.sin(angle)
            M[:3, 3] = centroid - M[:3, :3] @ centroid  # about the centroid
            starts.append(T @ M)
    return torch.stack(starts)


def restart_refinement(
    points_src: torch.Tensor | RefineCloud,
    points_tgt: torch.Tensor | RefineCloud,
    T: torch.Tensor,
    voxel_size: float,
    parallel: Callable[[Sequence[Callable[[], torch.Tensor]]], list] | None = None,
) -> Restarts:
    """Refine again from ``T (4, 4)`` and from the starts around it of :func:`restart_starts`,
    on at most ``RESTART_POINTS`` source points per level: a right result sits in a basin
    the restarts come back to, and no restart ends elsewhere with a better fitness.

    Args: as :func:`refine_multiscale`; ``parallel`` splits the searches in halves.
    """
    src, tgt = _prepared(points_src, voxel_size), _prepared(points_tgt, voxel_size)
    centroid = src.source(0, RESTART_POINTS).mean(0)
    starts = restart_starts(T.detach().to(torch.float64).cpu(), centroid)
    ends, fitness = refine_starts(
        src, tgt, starts, voxel_size, max_source_points=RESTART_POINTS, parallel=parallel
    )
    return Restarts(ends, fitness, float(voxel_size))


def refine_starts(
    points_src: torch.Tensor | RefineCloud,
    points_tgt: torch.Tensor | RefineCloud,
    starts: torch.Tensor,
    voxel_size: float,
    max_source_points: int = MAX_SOURCE_POINTS,
    parallel: Callable[[Sequence[Callable[[], torch.Tensor]]], list] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`refine_multiscale` from each of ``starts (S, 4, 4)`` at once: every step moves
    all the starts still moving with one nearest-point search and one
    :func:`point_to_plane_steps` (a start stops at a level as it would alone: converged,
    too few correspondences, or ``ITERATIONS`` steps). The ends agree with
    :func:`refine_multiscale`'s up to rounding.

    Args: as :func:`refine_multiscale` (default degeneracy and sliding); ``parallel``
        splits the searches in halves.

    Returns:
        ``(S, 4, 4)`` float64 ends and ``(S,)`` float64 fitness of each (as
        :attr:`Refinement.fitness`).
    """
    src, tgt = _prepared(points_src, voxel_size), _prepared(points_tgt, voxel_size)
    T = starts.detach().to(device="cpu", dtype=torch.float64).clone()
    fitness = torch.zeros(len(T), dtype=torch.float64)
    for level, (size, dist, _) in enumerate(src.levels):
        p = src.source(level, max_source_points)
        q, n, index = tgt.target(level)
        if len(p) < MIN_CORRESPONDENCES or len(q) < MIN_CORRESPONDENCES:
            break
        search = _StartSearch(index, SEARCH_REACH[level], RESEARCH * size, parallel)
        moving = torch.arange(len(T))
        for _ in range(ITERATIONS):
            if len(moving) == 0:
                break
            moved = p @ T[moving, :3, :3].transpose(1, 2) + T[moving, None, :3, 3]  # (A, K, 3)
            near = search.nearest(moving, moved)
            ok = near.distance2 <= dist**2  # (A, K)
            fitness[moving] = ok.double().mean(1)
            enough = ok.sum(1) >= MIN_CORRESPONDENCES  # fewer: the start stops at this level
            moving, moved, ok, j = moving[enough], moved[enough], ok[enough], near.index[enough]
            j = j.clamp_min(0)
            steps = point_to_plane_steps(moved, q[j], n[j], ok.double())
            T[moving] = steps @ T[moving]
            cos = (steps[:, :3, :3].diagonal(dim1=1, dim2=2).sum(1) - 1) / 2
            angle = torch.arccos(cos.clamp(-1.0, 1.0))
            shift = torch.linalg.vector_norm(steps[:, :3, 3], dim=1)
            moving = moving[~((angle < TOLERANCE) & (shift < TOLERANCE * voxel_size))]
    return T, fitness


class _StartSearch:
    """The nearest-point searches of :func:`refine_starts` at one level: each start's
    candidates, gathered again only once its points have moved ``research`` since."""

    def __init__(self, index: CellIndex, reach: int, research: float, parallel) -> None:
        self.index, self.reach, self.research, self.parallel = index, reach, research, parallel
        self.anchor: dict[int, torch.Tensor] = {}
        self.candidates: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def nearest(self, starts: torch.Tensor, moved: torch.Tensor) -> Nearest:
        """:class:`Nearest` of ``moved (A, K, 3)``, the points of ``starts (A,)``, as
        ``(A, K)`` tensors."""
        ids = starts.tolist()
        stale = [
            a
            for a, s in enumerate(ids)
            if s not in self.anchor
            or float((moved[a] - self.anchor[s]).abs().max()) > self.research
        ]
        if stale:
            queries = moved[stale].reshape(-1, 3)
            found = _search(self.index, queries, self.reach, self.parallel)
            coordinates = candidate_coordinates(self.index, found).chunk(len(stale), dim=1)
            for a, part, coords in zip(stale, found.chunk(len(stale)), coordinates, strict=True):
                self.anchor[ids[a]] = moved[a]
                self.candidates[ids[a]] = (part, coords)
        candidates = torch.cat([self.candidates[s][0] for s in ids])
        coordinates = torch.cat([self.candidates[s][1] for s in ids], dim=1)
        near = nearest_of(self.index, moved.reshape(-1, 3), candidates, coordinates)
        return Nearest(near.index.view(len(ids), -1), near.distance2.view(len(ids), -1))
