"""The robust fit of one pair's correspondences, its refinement and restarts, and the verdict.

:class:`Solver` holds the kept points of both clouds, the full clouds the refinement runs on,
the feature and refinement voxels and the settings of a
:class:`~byoc_cli.pipeline.register.RegisterConfig`. :meth:`Solver.solve` fits a set of
correspondences (:func:`fit_robust`: randomized Procrustes or RANSAC), refines the fit
(``"multiscale"``, or measures it as it is), restarts the refinement when the result can reach
the restart floor (:func:`run_restarts`) and judges the end
(:class:`byoc_cli.pipeline.verdict.Judge`); with ``structure_check`` (the recipe's
``matching.turns``), a result that reaches the gate is checked against its turns about the up
axis, and a turn that fits clearly better taken instead (:meth:`Solver.check_structure`).
"""

from __future__ import annotations

import math
import time
import warnings
from typing import TYPE_CHECKING

import torch

from byoc_cli.errors import RegistrationError
from byoc_cli.fitting import randomized_procrustes, ransac, spatial_compatibility
from byoc_cli.pipeline.refine import Refinement, measure_fit, refine_multiscale
from byoc_cli.pipeline.restarts import restart_refinement
from byoc_cli.pipeline.structure_check import (
    ADOPT_GAIN,
    RIVAL_MARGIN,
    VETOED_CONFIDENCE,
    RivalCheck,
)
from byoc_cli.pipeline.verdict import NO_RESTARTS, Judge, Verdict

if TYPE_CHECKING:
    from byoc_cli.pipeline.register import RegisterConfig

#: a restart's end replaces the refined result when its fitness is higher by this
SWITCH_GAIN = 0.01


class Solver:
    """The robust fit, refinement and verdict of one pair's correspondences: the kept points
    of ``src`` and ``tgt``, the ``full`` clouds the refinement runs on, the feature and
    refinement voxels and the settings of ``config``."""

    def __init__(self, src, tgt, full, voxel_size, refine_voxel, config, parallel):
        self.src, self.tgt, self.full = src, tgt, full
        self.voxel_size, self.refine_voxel = voxel_size, refine_voxel
        self.config, self.parallel = config, parallel
        self.threshold = config.inlier_factor * voxel_size
        #: the translation below which a result is identity-like
        #: (:func:`byoc_cli.pipeline.register.identity_like`)
        self.still = config.inlier_factor * refine_voxel
        self._rivals = None  # the structure check's RivalCheck, made on first use

    def solve(self, fitted, judged, generator, timer) -> tuple[Refinement, Verdict]:
        """The refined robust fit of the correspondences ``fitted`` (``p, q (K, 3)``, ``w
        (K,)``) and its verdict on the correspondences ``judged``; ``timer(stage, start)``
        adds the seconds since ``start`` to ``stage`` and returns the time now.

        Raises:
            RegistrationError: the fit is degenerate (every minimal set rejected).
        """
        config, full = self.config, self.full
        start = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fit = fit_robust(*fitted, config, self.threshold, generator)
        if caught:  # a degenerate fit (every minimal set rejected): no transform to report
            reason = str(caught[0].message).split(";")[0]  # not the estimator's fallback
            raise RegistrationError(f"no transform could be fitted ({reason})")
        T = fit.T_tgt_src.to(torch.float64)
        start = timer("fit", start)
        if config.refine == "multiscale":
            refinement = refine_multiscale(*full, T, self.refine_voxel, parallel=self.parallel)
            start = timer("refine", start)
        else:  # the fit cues of the result as it is
            refinement = measure_fit(*full, T, self.refine_voxel)
            start = timer("measure", start)
        judge = Judge(self.src, self.tgt, judged, T, self.voxel_size, self.threshold, config)
        verdict = judge(refinement, NO_RESTARTS)
        start = timer("verify", start)
        # restarts can only lower the confidence of a result that stays where it is (their
        # cues at their best are the ones above), so a result that cannot reach the floor
        # skips them
        if (
            config.refine == "multiscale"
            and config.restarts
            and verdict.confidence >= config.restart_floor
        ):
            refinement, restart_cues = run_restarts(
                full, refinement, self.refine_voxel, self.parallel
            )
            start = timer("restarts", start)
            verdict = judge(refinement, restart_cues)
            start = timer("verify", start)
        checked = config.structure_check or config.turn_rooms
        if checked and verdict.confidence >= config.min_confidence:
            refinement, verdict = self.check_structure(refinement, verdict, judge)
            timer("structure", start)
        return refinement, verdict

    def check_structure(
        self, refinement: Refinement, verdict: Verdict, judge: Judge
    ) -> tuple[Refinement, Verdict]:
        """``refinement`` and ``verdict`` with the cue ``structure_rival``
        (:func:`structure_rival`), the confidence capped at :data:`VETOED_CONFIDENCE` when a
        turned rival fits the clutter as well, less well by at most :data:`RIVAL_MARGIN`
        (the result is ambiguous). On large panoramas (``config.turn_rooms``) whose clouds are
        rooms (:attr:`~byoc_cli.pipeline.structure_check.RivalCheck.room_like`) each turn also
        starts where it overlays the most of the target, and a rival that fits better by
        :data:`ADOPT_GAIN` is adopted: refined, judged by ``judge`` and checked against its
        own turns in turn (cue ``structure_adopted``: the gain it was adopted for). A large
        panorama that is not a room (an object centred on its origin) is left unchecked
        unless ``config.structure_check``."""
        rooms = self.config.turn_rooms and self._checker().room_like
        if not rooms and not self.config.structure_check:  # a large panorama, not a room
            return refinement, verdict
        rival = self._checker()(refinement.T_tgt_src, correlate=rooms)
        adopted = rooms and rival.gain >= ADOPT_GAIN
        if adopted:
            start = torch.from_numpy(rival.T_tgt_src)
            refinement = refine_multiscale(
                *self.full, start, self.refine_voxel, parallel=self.parallel
            )
            verdict = judge(refinement, NO_RESTARTS)
            gain = rival.gain
            rival = self._checker()(refinement.T_tgt_src, correlate=True)
        cues = {**verdict.cues, "structure_rival": rival.gain}
        if adopted:
            cues["structure_adopted"] = gain
        confidence = verdict.confidence
        if not rival.gain <= -RIVAL_MARGIN and not math.isnan(rival.gain):
            confidence = min(confidence, VETOED_CONFIDENCE)
        return refinement, verdict._replace(cues=cues, confidence=confidence)

    def _checker(self) -> RivalCheck:
        """The :class:`RivalCheck` of this solver's clouds (their structures found once)."""
        if self._rivals is None:
            self._rivals = RivalCheck(
                self.src.points,
                self.tgt.points,
                self.voxel_size,
                self.full,
                self.refine_voxel,
                self.parallel,
            )
        return self._rivals


def run_restarts(clouds, refinement: Refinement, voxel_size: float, parallel):
    """The refinement to report and the restart cues: :func:`restart_refinement` around
    ``refinement``'s result; where the best end lies elsewhere and its fitness is higher by
    ``SWITCH_GAIN``, the full refinement from there replaces it."""
    restarts = restart_refinement(*clouds, refinement.T_tgt_src, voxel_size, parallel=parallel)
    pick = restarts.best()
    if (
        bool(restarts.same_place(0)[pick])
        or restarts.fitness[pick] - restarts.fitness[0] <= SWITCH_GAIN
    ):
        pick = 0
    else:
        refinement = refine_multiscale(*clouds, restarts.ends[pick], voxel_size, parallel=parallel)
    return refinement, {
        "restart_return": restarts.returned(pick),
        "restart_gain": restarts.gain(pick),
    }


def fit_robust(
    p: torch.Tensor,
    q: torch.Tensor,
    w: torch.Tensor,
    config: RegisterConfig,
    threshold: float,
    generator: torch.Generator,
):
    """The robust estimator of ``config`` on correspondences ``p, q (K, 3)``, ``w (K,)``."""
    if config.estimator == "procrustes":
        return randomized_procrustes(
            p,
            q,
            w,
            num_subsets=config.num_subsets,
            subset_size=config.subset_size,
            generator=generator,
        )
    if config.estimator == "sc2":
        return spatial_compatibility(p, q, threshold, weight=w, generator=generator)
    return ransac(
        p,
        q,
        inlier_threshold=threshold,
        max_iterations=config.ransac_iterations,
        confidence=config.ransac_confidence,
        generator=generator,
    )
