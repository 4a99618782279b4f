"""Turned tries of the learned features: scans turned far apart about the vertical.

The learned features were trained on views turned by at most 60 deg
(:mod:`byoc_cli.training.config`, ``aug_rotation_deg``); two scans of a room taken by a
terrestrial scanner from two stations, or an object turned on a turntable, differ by any
angle about the vertical, and there the features of the two clouds stop matching: on the 18
Kinect and RealSense pairs of ``benchmarks/turns.py`` with the source turned 180 deg about its
up axis, 4 came back wrong with exit 0. When the first result is below :data:`TURN_BELOW`,
the source's features are extracted again from the source turned by :data:`TURNS_DEG` about its
up axis (:func:`~byoc_cli.geometry.orientation.up_axis`), each matched against the target's features
as they are (their positions stay the source's own, so the fit, the refinement and the
verdict see the same clouds), and the most confident result replaces the first when it is
more confident by :data:`TURN_GAIN`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from byoc_cli.pipeline.results import Features, Registration

#: the turns are tried when the first result's confidence is below this
TURN_BELOW = 0.95
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


def with_turns(
    made: Any, first: Registration, pair: tuple[Features, Features], turned, settings: dict
) -> tuple[Registration, bool]:
    """``(registration, done)``: ``first`` (the learned result of ``pair``, source and target
    features, by ``made.match_alone`` with ``settings``) or the turned one of
    :func:`best_turn` when ``turned`` (:func:`source_turner`'s) is given and ``first`` is
    below :data:`TURN_BELOW`; ``done``: it is ambiguous or at least :data:`TURN_SURE`, and the
    FPFH fallback that a first result below the gate calls for is not to run."""
    if turned is None or first.confidence >= TURN_BELOW:
        return first, False
    src, tgt = pair

    def again(features: Features) -> Registration:
        return made.match_alone(features, tgt, **settings)

    kept = best_turn(first, src.cloud, turned, again, made.fallback_below, src.scale)
    return kept, kept.turns["ambiguous"] or kept.confidence >= TURN_SURE


def source_turner(made: Any, features: Features, scale, label: str, voxel: tuple):
    """``(T (4, 4)) -> Features`` or None: with ``made.turns`` and a cloud in ``features``
    (the source's, at ``voxel``: ``(voxel_size, refine_voxel, keep)``; ``scale`` and ``label``
    as ``made.extract_points`` takes them), the source's features extracted from its cloud
    turned by ``T``, at the positions of its points (its refinement levels serve every turn);
    None otherwise."""
    points = features.cloud
    if not made.turns or points is None:
        return None

    def turned(T: np.ndarray) -> Features:
        got = made.extract_points(points @ T[:3, :3].T + T[:3, 3], scale, label, *voxel)
        return got._replace(
            points=points[got.point_index], cloud=features.cloud, origin=features.origin
        )

    return turned


def best_turn(
    first: Registration,
    points: np.ndarray,
    turned: Callable[[np.ndarray], Features],
    match: Callable[[Features], Registration],
    gate: float,
    scale: float = 1.0,
) -> Registration:
    """``first``, or the most confident of the source turned by :data:`TURNS_DEG` about the
    up axis of ``points (N, 3)`` (the source, metres) where it beats ``first`` by
    :data:`TURN_GAIN`; ``turned``: :func:`source_turner`'s; ``match``: registers a source's
    features against the target's; ``gate``: the run's ``min_confidence``; ``scale``: the
    input's factor to metres (``points`` are the input times ``scale``; the results'
    ``T_tgt_src`` are in the input's units).

    The result's ``turns`` says what was tried (``up_axis``, ``tries``: each turn's degrees,
    confidence and ``T_tgt_src``, ``kept_deg``) and whether it is ``ambiguous``: another try
    close to it in confidence ends elsewhere (a scene that fits turned, as a room whose
    halves look alike). An ambiguous result does not pass.
    """
    from byoc_cli.geometry.orientation import turn_about, up_axis

    start = time.perf_counter()
    centre = points.mean(axis=0)
    axis = up_axis(points - centre)
    tries = [(0.0, first)]
    tries += [(deg, match(turned(turn_about(axis, deg, centre)))) for deg in TURNS_DEG]
    deg, best = max(tries[1:], key=lambda t: t[1].confidence)
    if best.confidence < first.confidence + TURN_GAIN:
        deg, best = tries[0]
    # where each try puts the source's median point, in the input's coordinates and units: the
    # translations of georeferenced scans (hundreds of kilometres out) differ by kilometres
    # for 0.1 deg, and a stray point far away would drag a mean
    at = np.median(points, axis=0) / scale
    rivals = [
        (d, r)
        for d, r in tries
        if r is not best
        and r.confidence >= max(gate, best.confidence - AMBIGUOUS_WITHIN)
        and not _same_place(r.T_tgt_src, best.T_tgt_src, best.voxel_size / scale, at)
    ]
    report = {
        "up_axis": [round(float(a), 6) for a in axis],
        "tries": [
            {"degrees": d, "confidence": r.confidence, "T_tgt_src": r.T_tgt_src.tolist()}
            for d, r in tries
        ],
        "kept_deg": deg,
        "ambiguous": bool(rivals),
    }
    timings = dict(best.timings)
    timings["turns"] = time.perf_counter() - start
    passed = best.passed and not rivals
    return best._replace(turns=report, timings=timings, passed=passed)


def _same_place(T_a: np.ndarray, T_b: np.ndarray, voxel: float, at: np.ndarray) -> bool:
    """Whether ``T_a`` and ``T_b (4, 4)`` turn within SAME_DEG of each other and move the
    point ``at (3,)`` (the source's centre) to within SAME_VOXELS voxels of each other."""
    from byoc_cli.pipeline.local import correction

    apart = correction(T_a, T_b, at)
    return apart.rotation_deg < SAME_DEG and apart.translation < SAME_VOXELS * voxel
