"""The structure check of a result about to pass the gate: does the source, turned 90, 180 or
270 deg about the up axis, fit what is not floor, ceiling or wall better, or as well?

A room turned onto itself about its up axis fits its large planes (floor, ceiling, walls) as
well as the truth, and so the fit cues of the verdict; what stands in the room does not
(docs/experiments/2026-11-27-room-structure-cue.md). :class:`RivalCheck` turns the result
about the target's up axis, moves each turn so the source's large planes overlay the
target's (on rooms, each turn starts a second time where the turned source overlays the
most of the target: :func:`~byoc_cli.geometry.structure.turned_alternatives`), refines the
starts together (:func:`~byoc_cli.pipeline.restarts.refine_starts`) and returns how much
better the best of them that ends elsewhere fits the source's clutter than the result, and
that rival (:func:`byoc_cli.geometry.structure.clutter_shares`).
:class:`~byoc_cli.pipeline.solve.Solver` caps the confidence of a result whose rival fits its
clutter less well by no more than :data:`RIVAL_MARGIN` (a room that looks the same turned:
the result is ambiguous), and on rooms takes a rival that fits better by :data:`ADOPT_GAIN`
instead of the result (refined, judged and checked in turn). It runs with the recipe's
``matching.turns`` (``--turns``: scans declared turned about the vertical; the FPFH fallback
on large panoramas), and on every result where the clouds are large panoramas
(:func:`~byoc_cli.pipeline.fallback.large_panoramas`) that are rooms
(:attr:`RivalCheck.room_like`). On the 14 simulated rooms of docs/rooms.md (three seeds)
right results read -0.45 to -0.10; the rivals taken gained 0.11 to 0.40 and each ended
right; a point-symmetric room's half turn, one small box apart, -0.02 (refused).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.geometry.structure import clutter_shares, structure, turned_alternatives
from byoc_cli.pipeline.local import correction
from byoc_cli.pipeline.restarts import RESTART_POINTS, refine_starts

#: a turned rival whose clutter fit is lower than the result's by less than this (or higher)
#: vetoes the result: another pose fits as well
RIVAL_MARGIN = 0.05
#: the clutter fit's radius, in feature voxels
RIVAL_RADIUS = 2.0
#: the confidence of a vetoed result at most
VETOED_CONFIDENCE = 0.1
#: a room: at least this share of each cloud's voxels lies on its large planes (the simulated
#: rooms of docs/rooms.md 0.71 to 0.89 at the check's voxel; the sample's real kitchen
#: fragments 0.26 to 0.66 at 5 cm, partial views of a cluttered room; objects centred in
#: millimetres 0.40 at most, the tabletop box 0.45)
ROOM_STRUCTURE = 0.5
#: a turned start refined to within this many degrees and feature voxels of the result (at
#: the source's centre) came back to it: not a rival
SAME_DEG, SAME_VOXELS = 5.0, 4.0
#: a turned rival whose clutter fit is higher than the result's by at least this replaces
#: the result (refined from there, judged again and checked against its own turns)
ADOPT_GAIN = 0.1


class Rival(NamedTuple):
    """Result of :func:`structure_rival`.

    Attributes:
        gain: how much better the best turned rival fits the source's clutter than the
            result (NaN when the source has no clutter or no large plane is found, or when
            every turn was refined back onto the result).
        T_tgt_src: ``(4, 4)`` float64 that rival, refined (None with a NaN ``gain``).
    """

    gain: float
    T_tgt_src: np.ndarray | None


class RivalCheck:
    """:func:`structure_rival` of one pair, its clouds' structures found once for every
    result checked (a result, then the rival it adopts).

    Args:
        points_src, points_tgt: ``(N, 3)``, ``(M, 3)`` the kept points (feature voxels).
        voxel_size: the feature voxel.
        full, refine_voxel: the clouds the refinement runs on and its voxel (the
            :class:`~byoc_cli.pipeline.solve.Solver`'s).
        parallel: runs the refinement's searches side by side.
    """

    def __init__(self, points_src, points_tgt, voxel_size, full, refine_voxel, parallel=None):
        self.src = structure(points_src.detach().cpu().double().numpy(), voxel_size)
        self.tgt = structure(points_tgt.detach().cpu().double().numpy(), voxel_size)
        self.voxel_size, self.full, self.refine_voxel = voxel_size, full, refine_voxel
        self.parallel = parallel

    @property
    def room_like(self) -> bool:
        """Whether both clouds are rooms: at least :data:`ROOM_STRUCTURE` of each lies on
        its large planes (floor, ceiling, walls)."""
        return min(self.src.mask.mean(), self.tgt.mask.mean()) >= ROOM_STRUCTURE

    def __call__(self, T: torch.Tensor, correlate: bool = False) -> Rival:
        """The :class:`Rival` of the result ``T (4, 4)`` (``T_tgt_src``); ``correlate``: each
        turn also starts where it overlays the most of the target
        (:func:`~byoc_cli.geometry.structure.turned_alternatives`; rooms)."""
        src, tgt, voxel = self.src, self.tgt, self.voxel_size
        if not src.mask.any() or src.mask.all() or not tgt.mask.any():
            return Rival(math.nan, None)
        T_np = T.detach().cpu().double().numpy()
        starts = torch.from_numpy(
            np.stack(turned_alternatives(src, tgt, T_np, voxel, correlate=correlate))
        )
        ends, _ = refine_starts(
            *self.full,
            starts,
            self.refine_voxel,
            max_source_points=RESTART_POINTS,
            parallel=self.parallel,
        )
        ends = [end for end in ends.numpy() if not _same_place(end, T_np, src.points, voxel)]
        if not ends:  # every turn came back to the result: no rival
            return Rival(math.nan, None)
        fits = clutter_shares(src, tgt, [T_np, *ends], RIVAL_RADIUS * voxel)
        best = int(np.argmax(fits[1:]))
        return Rival(float(fits[1 + best] - fits[0]), ends[best])


def _same_place(T_a: np.ndarray, T_b: np.ndarray, points: np.ndarray, voxel: float) -> bool:
    """Whether ``T_a`` and ``T_b (4, 4)`` turn within :data:`SAME_DEG` of each other and move
    the centre of ``points (N, 3)`` to within :data:`SAME_VOXELS` voxels of each other (a
    turned start refined back onto the result: a smooth object's turns, not a rival)."""
    degrees, apart = correction(T_a, T_b, points.mean(axis=0))
    return degrees < SAME_DEG and apart < SAME_VOXELS * voxel


def structure_rival(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    T: torch.Tensor,
    voxel_size: float,
    full,
    refine_voxel: float,
    parallel=None,
) -> Rival:
    """How much better the best turned rival of ``T (4, 4)`` fits the source's clutter than
    ``T`` does: the share of the source's non-structure points within :data:`RIVAL_RADIUS`
    feature voxels of a target point, the rival's minus ``T``'s, and that rival
    (:class:`RivalCheck`). Each turn starts twice (the large planes overlaid, and the most
    occupied cells: :func:`~byoc_cli.geometry.structure.turned_alternatives` with
    ``correlate``).

    Args:
        points_src, points_tgt: ``(N, 3)``, ``(M, 3)`` the kept points (feature voxels).
        T: the result ``T_tgt_src``.
        voxel_size: the feature voxel.
        full, refine_voxel: the clouds the refinement runs on and its voxel (the
            :class:`~byoc_cli.pipeline.solve.Solver`'s).
        parallel: runs the refinement's searches side by side.
    """
    return RivalCheck(points_src, points_tgt, voxel_size, full, refine_voxel, parallel)(T)
