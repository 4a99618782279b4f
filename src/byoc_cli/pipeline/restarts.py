"""Restarts of the refinement: the check of the basin a result sits in (the result turned
about each axis, each start refined, the ends compared; :func:`restart_refinement`), all
starts refined together (:func:`refine_starts`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.fitting.point_to_plane import point_to_plane_steps
from byoc_cli.geometry.neighbors import (
    CellIndex,
    Nearest,
    candidate_coordinates,
    nearest_of_arrays,
)
from byoc_cli.pipeline.refine import (
    ITERATIONS,
    MIN_CORRESPONDENCES,
    RESEARCH,
    TOLERANCE,
    cycle_end,
    cycle_period,
    search_candidates,
)
from byoc_cli.pipeline.refine_levels import (
    MAX_SOURCE_POINTS,
    SEARCH_REACH,
    RefineCloud,
    _prepared,
)

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
    too few correspondences, a cycle closed, or ``ITERATIONS`` steps). The ends agree with
    :func:`refine_multiscale`'s up to rounding.

    Args: as :func:`refine_multiscale` (default degeneracy and sliding); ``parallel``
        splits the searches in halves.

    Returns:
        ``(S, 4, 4)`` float64 ends and ``(S,)`` float64 fitness of each (as
        :attr:`Refinement.fitness`).
    """
    src, tgt = _prepared(points_src, voxel_size), _prepared(points_tgt, voxel_size)
    T = starts.detach().to(device="cpu", dtype=torch.float64).numpy().copy()
    fitness = np.zeros(len(T))
    for level, (size, dist, _) in enumerate(src.levels):
        p = src.source(level, max_source_points)
        q, n, index = tgt.target(level)
        if len(p) < MIN_CORRESPONDENCES or len(q) < MIN_CORRESPONDENCES:
            break
        # the steps in numpy, as refine_multiscale's (the searches stay in torch)
        p, q, n = p.numpy(), q.numpy(), n.numpy()
        search = _StartSearch(index, SEARCH_REACH[level], RESEARCH * size, parallel)
        moving = np.arange(len(T))
        history: dict[int, list[tuple]] = {s: [] for s in moving.tolist()}
        for i in range(ITERATIONS):
            if len(moving) == 0:
                break
            moved = p @ T[moving, :3, :3].transpose(0, 2, 1) + T[moving, None, :3, 3]  # (A, K, 3)
            near = search.nearest(moving, moved, i)
            ok = near.distance2 <= dist**2  # (A, K)
            fitness[moving] = ok.mean(1)
            enough = ok.sum(1) >= MIN_CORRESPONDENCES  # fewer: the start stops at this level
            moving, moved, ok, j = moving[enough], moved[enough], ok[enough], near.index[enough]
            j = np.maximum(j, 0)
            steps = point_to_plane_steps(moved, q[j], n[j], ok.astype(np.float64)).numpy()
            T[moving] = steps @ T[moving]
            cos = (np.trace(steps[:, :3, :3], axis1=1, axis2=2) - 1) / 2
            angle = np.arccos(np.clip(cos, -1.0, 1.0))
            shift = np.linalg.norm(steps[:, :3, 3], axis=1)
            moving = moving[~((angle < TOLERANCE) & (shift < TOLERANCE * voxel_size))]
            moving = _out_of_cycles(moving, T, fitness, history, i, search.searched)
    return torch.from_numpy(T), torch.from_numpy(fitness)


def _out_of_cycles(
    moving: np.ndarray,
    T: np.ndarray,
    fitness: np.ndarray,
    history: dict[int, list[tuple]],
    step: int,
    searched: dict[int, int],
) -> np.ndarray:
    """The starts of ``moving (A,)`` that go on after ``step`` of a level: each one's pose
    ``T[s] (4, 4)`` and the ``fitness[s]`` it was stepped from join its ``history``, and a
    start that closes a cycle (:func:`~byoc_cli.pipeline.refine.cycle_period`, no search
    since its first step: ``searched``, the step of each start's last search) takes the
    pose and fitness the level would end it with (in place) and stops, as
    :func:`~byoc_cli.pipeline.refine.refine_multiscale` does."""
    going = np.ones(len(moving), dtype=bool)
    for a, s in enumerate(moving.tolist()):
        history[s].append((T[s].copy(), fitness[s]))
        period = cycle_period(history[s], step - searched[s])
        if period:
            T[s], fitness[s] = cycle_end(history[s], period, ITERATIONS)
            going[a] = False
    return moving[going]


class _StartSearch:
    """The nearest-point searches of :func:`refine_starts` at one level: each start's
    candidates, gathered again only once its points have moved ``research`` since."""

    def __init__(self, index: CellIndex, reach: int, research: float, parallel) -> None:
        self.index, self.reach, self.research, self.parallel = index, reach, research, parallel
        self.origin = index.origin.numpy()
        self.anchor: dict[int, np.ndarray] = {}
        self.candidates: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.searched: dict[int, int] = {}  # the step of each start's last search

    def nearest(self, starts: np.ndarray, moved: np.ndarray, step: int) -> Nearest:
        """:class:`Nearest` of ``moved (A, K, 3)``, the points of ``starts (A,)`` at the
        level's ``step``, as ``(A, K)`` arrays."""
        ids = starts.tolist()
        stale = [
            a
            for a, s in enumerate(ids)
            if s not in self.anchor
            or float(np.abs(moved[a] - self.anchor[s]).max()) > self.research
        ]
        if stale:
            queries = torch.from_numpy(moved[stale].reshape(-1, 3))
            found = search_candidates(self.index, queries, self.reach, self.parallel)
            coordinates = candidate_coordinates(self.index, found).numpy()
            found = found.numpy()
            size = len(found) // len(stale)
            for k, a in enumerate(stale):
                self.anchor[ids[a]] = moved[a]
                self.searched[ids[a]] = step
                rows = slice(k * size, (k + 1) * size)
                self.candidates[ids[a]] = (found[rows], coordinates[:, rows])
        candidates = np.concatenate([self.candidates[s][0] for s in ids])
        coordinates = np.concatenate([self.candidates[s][1] for s in ids], axis=1)
        near = nearest_of_arrays(moved.reshape(-1, 3), self.origin, candidates, coordinates)
        return Nearest(near.index.reshape(len(ids), -1), near.distance2.reshape(len(ids), -1))
