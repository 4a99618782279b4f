"""Coarse-to-fine point-to-plane ICP that holds degenerate directions, on the CPU.

The refinement behind ``--refine multiscale`` (the default of learned features): three
levels of voxel size and correspondence distance, in multiples of the feature voxel ``v``:
``(v, 2v)``, ``(v/2, v)``, ``(0.4v, 0.6v)``, each up to 30 Gauss-Newton steps of
:func:`byoc_cli.fitting.point_to_plane.point_to_plane_step` (Open3D's ICP slides along
planes: ``point_to_plane.py`` says why and what is held). Voxel averages, normals and
nearest points come from voxel grids in PyTorch (:mod:`byoc_cli.geometry.neighbors`): no k-d
tree and no open3d, whose import alone took longer than the whole refinement does now. The
steps themselves (moving the points, picking the nearest candidates, the normal equations)
run in numpy: a step is a few dozen operations on a few thousand points, where torch's
per-call cost dominates and each call hands the interpreter lock to the other worker thread
of ``register-batch`` (``python benchmarks/init.py batch`` times it; CHANGELOG).

Correspondences: each source point's 8 nearest target points among the 27 cells of the
level's voxel around it are gathered once, and again only after a point has moved more
than half a voxel since; every step takes the nearest of those (within the level's
correspondence distance).

It runs on the full-resolution input points: the kept points of the feature voxel are too
coarse for the finest level (README, "Measured levers").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.fitting.point_to_plane import (
    DEGENERACY,
    SLIDING,
    PlaneStep,
    point_to_plane_step,
)
from byoc_cli.geometry.neighbors import (
    CellIndex,
    Nearest,
    candidate_coordinates,
    nearest_candidates,
    nearest_of,
    nearest_of_arrays,
)
from byoc_cli.pipeline.refine_levels import (
    LEVELS,
    MAX_SOURCE_POINTS,
    SEARCH_REACH,
    RefineCloud,
    _prepared,
)

__all__ = [
    "LEVELS",
    "SEARCH_REACH",
    "RefineCloud",
    "Refinement",
    "measure_fit",
    "refine_multiscale",
]

#: Gauss-Newton steps per level at most
ITERATIONS = 30
#: a level stops when a step moves less than this (radians, and multiples of v)
TOLERANCE = 4e-4
#: fewest correspondences for a step (fewer: the level is skipped)
MIN_CORRESPONDENCES = 6
#: nearest target points kept per source point between searches
CANDIDATES = 8
#: a new search once a source point has moved this many level voxels since the last
RESEARCH = 1.0
#: a step that ends within this (every number of ``T``) of where the step 2 to
#: :data:`MAX_CYCLE` steps before it ended closes a cycle, which the rest of its level would
#: repeat (rounding moves such a cycle by about 1e-16 a step; the T files' reference allows
#: 1e-12)
CYCLE = 1e-13
#: the longest such cycle looked for, in steps
MAX_CYCLE = 6


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
    T = T_init.detach().to(device="cpu", dtype=torch.float64).numpy().copy()
    rank, fitness, rmse, conditioning = 0, 0.0, float("nan"), 0.0
    for level, (size, dist, _) in enumerate(src.levels):
        p = src.source(level, max_source_points)  # levels, normals and searches: all threads
        q, n, index = tgt.target(level)
        if len(p) < MIN_CORRESPONDENCES or len(q) < MIN_CORRESPONDENCES:
            break
        # the steps in numpy: a step's few dozen small operations cost less there, and
        # numpy keeps the interpreter lock where each torch call hands it to the other worker
        p, planes, origin = p.numpy(), (q.numpy(), n.numpy()), index.origin.numpy()
        anchor, candidates, coordinates = None, None, None
        steps: list[tuple] = []  # (T, fitness, rmse, rank, conditioning) after each step
        searched = -1  # the last step that searched again
        for i in range(ITERATIONS):
            moved = p @ T[:3, :3].T + T[:3, 3]
            if anchor is None or float(np.abs(moved - anchor).max()) > RESEARCH * size:
                searched = i
                found = search_candidates(
                    index, torch.from_numpy(moved), SEARCH_REACH[level], parallel
                )
                candidates = found.numpy()
                coordinates = candidate_coordinates(index, found).numpy()
                anchor = moved
            near = nearest_of_arrays(moved, origin, candidates, coordinates)
            fitness, level_rmse, step = _meet(
                moved, near, planes, dist, voxel_size, (degeneracy, sliding)
            )
            if step is None:
                break
            rmse = level_rmse
            dT = step.T.numpy()
            T = dT @ T
            rank, conditioning = step.rank, float(step.eigenvalues[0])
            angle = math.acos(max(-1.0, min(1.0, (float(np.trace(dT[:3, :3])) - 1) / 2)))
            if angle < TOLERANCE and float(np.linalg.norm(dT[:3, 3])) < TOLERANCE * voxel_size:
                break
            steps.append((T, fitness, rmse, rank, conditioning))
            period = cycle_period(steps, i - searched)
            if period:  # the rest of the level repeats its last `period` steps
                T, fitness, rmse, rank, conditioning = cycle_end(steps, period, ITERATIONS)
                break
    return Refinement(torch.from_numpy(T), rank, fitness, rmse, conditioning)


def cycle_period(steps: list[tuple], unsearched: int) -> int:
    """The length (2 to :data:`MAX_CYCLE`) of the cycle that the last of a level's ``steps``
    (each ``(T (4, 4), ...)`` after a step) closes, ending within :data:`CYCLE` (every
    number) of where the step that many before it ended; 0: none. On smooth surfaces the
    nearest points change and change back, and a level goes round such a cycle until its
    ``ITERATIONS`` run out. A step is a function of the pose and the cached candidates, so
    when none of the cycle's steps but its first searched again (``unsearched``: the steps
    since the last search), every later step repeats the one a cycle before it, up to
    rounding: :func:`refine_multiscale` stops there and takes the state the level would end
    in."""
    last = steps[-1][0]
    for period in range(2, min(MAX_CYCLE, len(steps) - 1, unsearched + 1) + 1):
        if float(np.abs(last - steps[-1 - period][0]).max()) <= CYCLE:
            return period
    return 0


def cycle_end(steps: list[tuple], period: int, iterations: int) -> tuple:
    """The entry of ``steps`` (one per step of a level, the last closing a cycle of
    ``period`` steps: :func:`cycle_period`) that the level's step ``iterations - 1`` would end
    with, going round the cycle."""
    left = (iterations - len(steps)) % period  # the steps still to run, round the cycle
    return steps[-1 - (period - left) % period]


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
    near = nearest_of(index, moved, search_candidates(index, moved, SEARCH_REACH[level], None))
    near = Nearest(near.index.numpy(), near.distance2.numpy())
    fitness, rmse, step = _meet(moved.numpy(), near, (q.numpy(), n.numpy()), dist, voxel_size)
    if step is None:
        return Refinement(T, 0, fitness)
    return Refinement(T, step.rank, fitness, rmse, float(step.eigenvalues[0]))


def _meet(
    moved: np.ndarray,
    near: Nearest,
    planes: tuple[np.ndarray, np.ndarray],
    dist: float,
    voxel_size: float,
    held: tuple[float, float] = (DEGENERACY, SLIDING),
) -> tuple[float, float, PlaneStep | None]:
    """How source points ``moved (K, 3)`` meet their ``near`` target points (numpy arrays):
    the share within ``dist`` (metres; the fitness), their RMS distance in feature voxels,
    and the point-to-plane step onto the target ``planes`` (points ``(M, 3)``, normals
    ``(M, 3)``) with ``held = (degeneracy, sliding)``; residual nan and no step where fewer
    than ``MIN_CORRESPONDENCES`` meet."""
    ok = near.distance2 <= dist**2
    count = int(np.count_nonzero(ok))
    fitness = count / len(ok) if len(ok) else float("nan")
    if count < MIN_CORRESPONDENCES:
        return fitness, float("nan"), None
    rmse = math.sqrt(float(near.distance2[ok].astype(np.float64).mean())) / voxel_size
    j = near.index[ok]
    q, n = planes
    step = point_to_plane_step(moved[ok], q[j], n[j], degeneracy=held[0], sliding=held[1])
    return fitness, rmse, step


#: fewest source points whose search is split in two for ``parallel``
SPLIT_SEARCH = 4096


def search_candidates(
    index: CellIndex, queries: torch.Tensor, reach: int, parallel
) -> torch.Tensor:
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


# ------------------------------------------------------------------ pairs of many clouds
