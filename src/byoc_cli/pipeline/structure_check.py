"""The structure check of a result about to pass the gate: does the source, turned 90, 180 or
270 deg about the up axis, fit what is not floor, ceiling or wall as well as the result does?

A room turned onto itself about its up axis fits its large planes (floor, ceiling, walls) as
well as the truth, and so the fit cues of the verdict; what stands in the room does not
(docs/experiments/2026-11-27-room-structure-cue.md). :func:`structure_rival` turns the result
about the target's up axis, moves each turn so the source's large planes overlay the
target's, refines the turns together (:func:`~byoc_cli.pipeline.restarts.refine_starts`) and
returns how much better the best of them fits the source's clutter than the result
(:func:`byoc_cli.geometry.structure.clutter_fit`). :class:`~byoc_cli.pipeline.solve.Solver`
caps the confidence of a result whose rival fits its clutter less well by no more than
:data:`RIVAL_MARGIN` (a turn that fits better, or a room that looks the same turned: the
result is ambiguous), when the recipe's ``matching.turns`` is on (``--turns``: scans declared
turned about the vertical; and the FPFH fallback on panoramic laser scans of rooms,
:mod:`byoc_cli.pipeline.fallback`; the check costs a refinement of three starts per result
that passes). On the simulated rooms of docs/rooms.md right results read -0.62 to -0.11,
and -0.71 to -0.02 in the point-symmetric rooms, whose half turn differs by one small box;
wrong ones -0.03 to +0.50.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from byoc_cli.geometry.structure import clutter_fit, structure, turned_alternatives
from byoc_cli.pipeline.restarts import RESTART_POINTS, refine_starts

#: a turned rival whose clutter fit is lower than the result's by less than this (or higher)
#: vetoes the result: another pose fits as well
RIVAL_MARGIN = 0.05
#: the clutter fit's radius, in feature voxels
RIVAL_RADIUS = 2.0
#: the confidence of a vetoed result at most
VETOED_CONFIDENCE = 0.1


def structure_rival(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    T: torch.Tensor,
    voxel_size: float,
    full,
    refine_voxel: float,
    parallel=None,
) -> float:
    """How much better the best turned rival of ``T (4, 4)`` fits the source's clutter than
    ``T`` does: the share of the source's non-structure points within :data:`RIVAL_RADIUS`
    feature voxels of a target point, the rival's minus ``T``'s (NaN when the source has no
    clutter or no large plane is found).

    Args:
        points_src, points_tgt: ``(N, 3)``, ``(M, 3)`` the kept points (feature voxels).
        T: the result ``T_tgt_src``.
        voxel_size: the feature voxel.
        full, refine_voxel: the clouds the refinement runs on and its voxel (the
            :class:`~byoc_cli.pipeline.solve.Solver`'s).
        parallel: runs the refinement's searches side by side.
    """
    src = structure(points_src.detach().cpu().double().numpy(), voxel_size)
    tgt = structure(points_tgt.detach().cpu().double().numpy(), voxel_size)
    if not src.mask.any() or src.mask.all() or not tgt.mask.any():
        return math.nan
    T_np = T.detach().cpu().double().numpy()
    starts = torch.from_numpy(np.stack(turned_alternatives(src, tgt, T_np, voxel_size)))
    ends, _ = refine_starts(
        *full, starts, refine_voxel, max_source_points=RESTART_POINTS, parallel=parallel
    )
    radius = RIVAL_RADIUS * voxel_size
    own = clutter_fit(src, tgt, T_np, radius).clutter
    best = max(clutter_fit(src, tgt, end, radius).clutter for end in ends.numpy())
    return float(best - own)
