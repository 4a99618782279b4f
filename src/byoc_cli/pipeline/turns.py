"""Turned tries of the learned features: scans turned far apart about the vertical.

The learned features were trained on views turned by at most 60 deg
(:mod:`byoc_cli.training.config`, ``aug_rotation_deg``); two scans of a room taken by a
terrestrial scanner from two stations, two fragments of a Kinect sweep (in 3DLoMatch 42 % of
the pairs are turned more than 60 deg), or an object turned on a turntable, differ by any
angle about the vertical, and there the features of the two clouds stop matching: on the 18
Kinect and RealSense pairs of ``benchmarks/turns.py`` with the source turned 180 deg about its
up axis, 4 came back wrong with exit 0. When the first result is below :data:`TURN_BELOW`,
the source's features are extracted again from the source turned by :data:`TURNS_DEG` about
the up axis (:func:`~byoc_cli.geometry.orientation.up_axis`), each matched against the
target's features as they are (their positions stay the source's own, so the fit, the
refinement and the verdict see the same clouds), and the most confident result replaces the
first when it is more confident by :data:`TURN_GAIN`.

The turns are about the target's up axis, the source's up axis first turned onto it
(:func:`~byoc_cli.geometry.orientation.aligning`): two hand-held cameras tilt differently (the
3DMatch sample's fragments 7 and 34, 27 deg), and a turn about the source's own axis leaves
that tilt on top of the features' tolerance. Where the two axes lie more than
:data:`ALIGN_MAX_DEG` apart one of them is not the vertical, and the turns are about the
source's own axis.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from byoc_cli.pipeline.results import Features, Registration
from byoc_cli.pipeline.retries import at_own_voxel, discounted

#: ``matching.turns`` of the ``byoc`` preset: the turned tries where the features see the
#: clouds at their own voxel (:func:`~byoc_cli.pipeline.retries.at_own_voxel`: depth frames,
#: RGB-D fragments), not where the auto voxel scaled them (laser scans of rooms, LiDAR,
#: objects), and without the structure check of ``--turns``
AUTO = "auto"
#: the turns are tried when the first result's confidence is below this
TURN_BELOW = 0.95
#: the same bound for the default's turns (:data:`AUTO`): on the 18 Kinect and RealSense pairs
#: of ``benchmarks/turns.py`` a right first result at 0.896 came back ambiguous (a turned try
#: fit the desk 92 deg away at 0.91); on the cut, frame and Kinect pairs of docs/low-overlap.md
#: no first result from 0.8 to 0.95 changed its outcome with the turns
AUTO_TURN_BELOW = 0.85
#: a turned result replaces the first when its confidence is higher by at least this
TURN_GAIN = 0.05
#: a turned result at or above this skips the FPFH fallback a first result below the gate
#: calls for (below it the more confident of the two is kept)
TURN_SURE = 0.8
#: the turns tried about the up axis, in degrees: every sixth of a turn, so that one lies
#: within 30 deg of any turn (the features were trained on views turned up to 60 deg)
TURNS_DEG = (60.0, 120.0, 180.0, 240.0, 300.0)
#: the kept result is ambiguous when another try within this much of its confidence (and
#: at or above the gate) ends elsewhere: more than SAME_DEG or SAME_VOXELS voxels away
AMBIGUOUS_WITHIN = 0.1
SAME_DEG, SAME_VOXELS = 5.0, 4.0
#: the source's up axis is turned onto the target's when they lie at most this far apart
#: (either sign); farther, one is not the vertical and the turns are about the source's own
ALIGN_MAX_DEG = 60.0
#: the aligned source is tried unturned too when the two axes lie more than this far apart
#: (closer, it is about the first try's source)
ALIGN_TRY_DEG = 10.0
#: a turned result kept is the most confident of several tries, more often wrong at a given
#: confidence than a first try (on which the model was calibrated): its odds are divided by
#: this (0.627 reads 0.457). On the turned cut pairs of docs/low-overlap.md (``cutr``: 27
#: turned results passed) 2 separates the 2 wrong ones (0.46, 0.56) from the 25 right (0.52
#: to 0.97, one lost); the retries' divisor, the number of tries (6), lost 12 right ones
TURN_ODDS = 2.0


def with_turns(
    made: Any, first: Registration, pair: tuple[Features, Features], turned, settings: dict
) -> tuple[Registration, bool]:
    """``(registration, done)``: ``first`` (the learned result of ``pair``, source and target
    features, by ``made.match_alone`` with ``settings``) or the turned one of
    :func:`best_turn` when ``turned`` (:func:`source_turner`'s) is given and ``first`` is
    below :data:`TURN_BELOW` (:data:`AUTO_TURN_BELOW` with ``made.turns`` :data:`AUTO`);
    ``done``: it is ambiguous or at least :data:`TURN_SURE`, and the
    FPFH fallback that a first result below the gate calls for is not to run."""
    below = AUTO_TURN_BELOW if made.turns == AUTO else TURN_BELOW
    if turned is None or first.confidence >= below:
        return first, False
    src, tgt = pair

    def again(features: Features) -> Registration:
        return made.match_alone(features, tgt, **settings)

    kept = best_turn(first, (src.cloud, tgt.cloud), turned, again, made.fallback_below, src.scale)
    return kept, kept.turns["ambiguous"] or kept.confidence >= TURN_SURE


def source_turner(made: Any, features: Features, scale, label: str, voxel: tuple):
    """``(T (4, 4)) -> Features`` or None: with ``made.turns`` and a cloud in ``features``
    (the source's, at ``voxel``: ``(voxel_size, refine_voxel, keep)``; ``scale`` and ``label``
    as ``made.extract_points`` takes them), the source's features extracted from its cloud
    turned by ``T``, at the positions of its points (its refinement levels serve every turn);
    None otherwise; None too with ``made.turns`` :data:`AUTO` where the features do not see
    the clouds at their own voxel."""
    points = features.cloud
    if not made.turns or points is None:
        return None
    if made.turns == AUTO and not at_own_voxel(made, features):
        return None

    def turned(T: np.ndarray) -> Features:
        got = made.extract_points(points @ T[:3, :3].T + T[:3, 3], scale, label, *voxel)
        return got._replace(
            points=points[got.point_index], cloud=features.cloud, origin=features.origin
        )

    return turned


def best_turn(
    first: Registration,
    clouds: tuple[np.ndarray, np.ndarray | None],
    turned: Callable[[np.ndarray], Features],
    match: Callable[[Features], Registration],
    gate: float,
    scale: float = 1.0,
) -> Registration:
    """``first``, or the most confident of the source turned by :data:`TURNS_DEG` about the
    up axis (:func:`turn_starts`) where it beats ``first`` by :data:`TURN_GAIN`;
    ``clouds``: the source's and the target's points ``(N, 3)``, ``(M, 3)`` (metres; the
    target None: turns about the source's own up axis); ``turned``: :func:`source_turner`'s;
    ``match``: registers a source's features against the target's; ``gate``: the run's
    ``min_confidence``; ``scale``: the input's factor to metres (``points`` are the input
    times ``scale``; the results' ``T_tgt_src`` are in the input's units).

    A turned result kept has its confidence discounted (:data:`TURN_ODDS`). The result's
    ``turns`` says what was tried (``up_axis``, the source's; ``target_up_axis``
    and ``tilt_deg``, the angle between the two; ``aligned``: the turns were about the
    target's axis; ``tries``: each one's degrees, whether its source was aligned, confidence
    and ``T_tgt_src``; ``kept_deg``; ``model_confidence``, the kept try's before the
    discount) and whether it is ``ambiguous``: another try close to it
    in confidence ends elsewhere (a scene that fits turned, as a room whose halves look
    alike). An ambiguous result does not pass.
    """
    start = time.perf_counter()
    points, target = clouds
    starts, report = turn_starts(points, target)
    tries = [(0.0, False, first)]
    tries += [(deg, aligned, match(turned(T))) for deg, aligned, T in starts]
    deg, _, best = max(tries[1:], key=lambda t: t[2].confidence)
    if best.confidence < first.confidence + TURN_GAIN:
        deg, _, best = tries[0]
    model_confidence = best.confidence
    # where each try puts the source's median point, in the input's coordinates and units: the
    # translations of georeferenced scans (hundreds of kilometres out) differ by kilometres
    # for 0.1 deg, and a stray point far away would drag a mean
    at = np.median(points, axis=0) / scale
    rivals = [
        (d, r)
        for d, _, r in tries
        if r is not best
        and r.confidence >= max(gate, best.confidence - AMBIGUOUS_WITHIN)
        and not _same_place(r.T_tgt_src, best.T_tgt_src, best.voxel_size / scale, at)
    ]
    report["tries"] = [
        {"degrees": d, "aligned": a, "confidence": r.confidence, "T_tgt_src": r.T_tgt_src.tolist()}
        for d, a, r in tries
    ]
    report.update(kept_deg=deg, ambiguous=bool(rivals), model_confidence=model_confidence)
    timings = dict(best.timings)
    timings["turns"] = time.perf_counter() - start
    if best is not first:  # a turned try: the pick of several
        best = best._replace(confidence=discounted(model_confidence, TURN_ODDS))
        best = best._replace(passed=best.passed and best.confidence >= gate)
    return best._replace(turns=report, timings=timings, passed=best.passed and not rivals)


def turn_starts(
    points: np.ndarray, target: np.ndarray | None
) -> tuple[list[tuple[float, bool, np.ndarray]], dict]:
    """The turned sources to try, ``(degrees, aligned, T (4, 4))`` each (``T`` moves the
    source ``points (N, 3)``), and the report of the axes (``up_axis``, ``target_up_axis``,
    ``tilt_deg``, ``aligned``).

    With ``target (M, 3)`` whose up axis lies within :data:`ALIGN_MAX_DEG` of the source's
    (either sign), the source's axis is first turned onto the target's about the source's
    centroid, and every turn of :data:`TURNS_DEG` is about the target's axis, the aligned but
    unturned source first when the axes lie more than :data:`ALIGN_TRY_DEG` apart; otherwise
    the turns are about the source's own axis."""
    from byoc_cli.geometry.orientation import aligning, turn_about, up_axis

    centre = points.mean(axis=0)
    axis = up_axis(points - centre)
    report: dict[str, Any] = {"up_axis": _rounded(axis), "target_up_axis": None}
    align, degrees, aligned = np.eye(4), TURNS_DEG, False
    if target is not None:
        onto = up_axis(target - target.mean(axis=0))
        axis = axis if float(axis @ onto) >= 0 else -axis
        tilt = math.degrees(math.acos(min(1.0, float(axis @ onto))))
        report.update(target_up_axis=_rounded(onto), tilt_deg=round(tilt, 3))
        if tilt <= ALIGN_MAX_DEG:
            align, axis, aligned = aligning(axis, onto, centre), onto, True
            degrees = ((0.0,) if tilt > ALIGN_TRY_DEG else ()) + TURNS_DEG
    report["aligned"] = aligned
    return [(deg, aligned, turn_about(axis, deg, centre) @ align) for deg in degrees], report


def _rounded(axis: np.ndarray) -> list[float]:
    return [round(float(a), 6) for a in axis]


def _same_place(T_a: np.ndarray, T_b: np.ndarray, voxel: float, at: np.ndarray) -> bool:
    """Whether ``T_a`` and ``T_b (4, 4)`` turn within SAME_DEG of each other and move the
    point ``at (3,)`` (the source's centre) to within SAME_VOXELS voxels of each other."""
    from byoc_cli.pipeline.local import correction

    apart = correction(T_a, T_b, at)
    return apart.rotation_deg < SAME_DEG and apart.translation < SAME_VOXELS * voxel
