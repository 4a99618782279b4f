"""The structure check of a result about to pass the gate: does the source, turned 90, 180 or
270 deg about the up axis, fit what is not floor, ceiling or wall better, or as well?

A room turned onto itself about its up axis fits its large planes (floor, ceiling, walls) as
well as the truth, and so the fit cues of the verdict; what stands in the room does not
(docs/experiments/2026-11-27-room-structure-cue.md). :class:`RivalCheck` turns the result
about the target's up axis, starts each turn twice (moved so the source's large planes
overlay the target's, and where the turned source overlays the most of the target:
:func:`~byoc_cli.geometry.structure.turned_alternatives`), refines the six starts together
(:func:`~byoc_cli.pipeline.restarts.refine_starts`) and returns how much better the best of
them fits the source's clutter than the result, and that rival
(:func:`byoc_cli.geometry.structure.clutter_shares`). :class:`~byoc_cli.pipeline.solve.Solver`
takes a rival that fits better by :data:`ADOPT_GAIN` instead of the result (refined, judged
and checked in turn), and caps the confidence of a result whose rival fits its clutter less
well by no more than :data:`RIVAL_MARGIN` (a room that looks the same turned: the result is
ambiguous). It runs when the recipe's ``matching.turns`` is on: ``--turns`` (scans declared
turned about the vertical), and every result on panoramic laser scans of rooms
(:func:`~byoc_cli.pipeline.fallback.panorama_changes`). On the 14 simulated rooms of
docs/rooms.md (three seeds) right results read -0.45 to -0.10; the rivals taken gained 0.11
to 0.40 and each ended right; a point-symmetric room's half turn, one small box apart,
-0.02 (refused).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.geometry.structure import clutter_shares, structure, turned_alternatives
from byoc_cli.pipeline.restarts import RESTART_POINTS, refine_starts

#: a turned rival whose clutter fit is lower than the result's by less than this (or higher)
#: vetoes the result: another pose fits as well
RIVAL_MARGIN = 0.05
#: the clutter fit's radius, in feature voxels
RIVAL_RADIUS = 2.0
#: the confidence of a vetoed result at most
VETOED_CONFIDENCE = 0.1
#: a turned rival whose clutter fit is higher than the result's by at least this replaces
#: the result (refined from there, judged again and checked against its own turns)
ADOPT_GAIN = 0.1


class Rival(NamedTuple):
    """Result of :func:`structure_rival`.

    Attributes:
        gain: how much better the best turned rival fits the source's clutter than the
            result (NaN when the source has no clutter or no large plane is found).
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
        correlate: each turn also starts where it overlays the most of the target
            (:func:`~byoc_cli.geometry.structure.turned_alternatives`; laser scans of rooms).
    """

    def __init__(
        self, points_src, points_tgt, voxel_size, full, refine_voxel, parallel=None, correlate=False
    ):
        self.src = structure(points_src.detach().cpu().double().numpy(), voxel_size)
        self.tgt = structure(points_tgt.detach().cpu().double().numpy(), voxel_size)
        self.voxel_size, self.full, self.refine_voxel = voxel_size, full, refine_voxel
        self.parallel, self.correlate = parallel, correlate

    def __call__(self, T: torch.Tensor) -> Rival:
        """The :class:`Rival` of the result ``T (4, 4)`` (``T_tgt_src``)."""
        src, tgt, voxel = self.src, self.tgt, self.voxel_size
        if not src.mask.any() or src.mask.all() or not tgt.mask.any():
            return Rival(math.nan, None)
        T_np = T.detach().cpu().double().numpy()
        starts = torch.from_numpy(
            np.stack(turned_alternatives(src, tgt, T_np, voxel, correlate=self.correlate))
        )
        ends, _ = refine_starts(
            *self.full,
            starts,
            self.refine_voxel,
            max_source_points=RESTART_POINTS,
            parallel=self.parallel,
        )
        fits = clutter_shares(src, tgt, [T_np, *ends.numpy()], RIVAL_RADIUS * voxel)
        best = int(np.argmax(fits[1:]))
        return Rival(float(fits[1 + best] - fits[0]), ends[best].numpy())


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
