"""Tries of the matching under the next seeds when the first result is below the gate.

At low overlap the learned features' correspondences hold a few inliers in a thousand, and
whether the robust fit finds the one right pose among them depends on the seeded subset of
points that enters matching and on RANSAC's draws: on the 96 cut pairs of
``benchmarks/cut_pairs.py`` (10-30 % overlap, docs/low-overlap.md), seeds 0, 1 and 2 each
register 50-51 % of the pairs, and at least one of the three 62.5 %. So when the first
result is below the gate, the matching, the fit and the refinement run again (the features
are not extracted again) with the seeds after the recipe's, up to ``gate.retries`` times.

A result picked as the most confident of several tries is wrong more often at a given
confidence than a first result, on which the confidence model was calibrated: on the same
pairs, retries kept from the gate (0.45) on passed 16 wrong results against the first tries'
10. So a retry's confidence is :func:`discounted` for the tries it was picked from (its odds
divided by their number: 0.7 of the third try reads 0.44), the most confident try after the
discount is kept (its ``T`` may be the right one even below the gate), and the tries stop at
the first one that passes. Of the 15 retries of the development sets that reached 0.7 or
more (average 0.86), 10 were right (67 %); discounted, they average 0.73.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from byoc_cli.errors import RegistrationError

if TYPE_CHECKING:
    from byoc_cli.pipeline.results import Features, Registration


def discounted(confidence: float, tries: int) -> float:
    """The confidence of a result picked as the most confident of ``tries`` tries: the
    model's odds ``c / (1 - c)`` divided by ``tries`` (1: ``confidence`` as it is)."""
    if tries <= 1 or confidence >= 1.0:
        return confidence
    odds = confidence / (1.0 - confidence) / tries
    return min(confidence, odds / (1.0 + odds))


def retry_seed(seed: int, k: int) -> int:
    """The seed of the ``k``-th retry (``k >= 1``) of a run seeded ``seed``: the next ones,
    wrapping at 2**64 (the range of a recipe's seed)."""
    return (seed + k) % 2**64


def with_retries(
    first: Registration, again: Callable[[int], Registration], seed: int, retries: int, gate: float
) -> Registration:
    """``first`` or the most confident retry after the :func:`discounted` confidence (the
    tries stop at the first one that passes ``gate``).

    Args:
        first: the first result of the pair, with the run's ``seed``.
        again: the same registration of the same features with another seed.
        seed: the run's seed; the ``k``-th retry runs with :func:`retry_seed` ``(seed, k)``.
        retries: most retries (0: none).
        gate: the run's ``gate.min_confidence``; a first result at or above it is not retried.

    Returns:
        The kept result; when retries ran, its ``retries`` holds the ``first_confidence``
        and ``first_T_tgt_src``, the ``tries`` (each retry's ``seed``, discounted
        ``confidence``, the model's ``model_confidence`` and ``T_tgt_src``: every pose tried
        below the gate), ``kept_seed`` (None: the first result was kept) and
        ``seconds``, and its ``timings["retries"]`` the seconds of the retries (a retry that
        raised ``RegistrationError`` is listed with its ``error`` and no confidence). A kept retry
        has the discounted confidence (``passed`` from it), and carries the first result's
        recipe and seed (the run that made it).
    """
    if retries < 1 or first.confidence >= gate:
        return first
    start = time.perf_counter()
    tries, kept = [], None
    for k in range(1, retries + 1):
        try:
            other = again(retry_seed(seed, k))
        except RegistrationError as exc:  # no transform under this seed: the next one
            tries.append({"seed": retry_seed(seed, k), "confidence": None, "error": str(exc)})
            continue
        confidence = discounted(other.confidence, k + 1)
        tries.append(
            {"seed": other.seed, "confidence": confidence, "model_confidence": other.confidence}
            | {"T_tgt_src": other.T_tgt_src.tolist()}
        )
        if confidence > (first if kept is None else kept).confidence:
            kept = other._replace(confidence=confidence, passed=confidence >= gate)
        if kept is not None and kept.passed:
            break
    seconds = time.perf_counter() - start
    note = {
        "first_confidence": first.confidence,
        "first_T_tgt_src": first.T_tgt_src.tolist(),
        "tries": tries,
        "kept_seed": None if kept is None else kept.seed,
        "seconds": seconds,
    }
    if kept is None:
        return first._replace(timings={**first.timings, "retries": seconds}, retries=note)
    return kept._replace(
        timings={**kept.timings, "retries": seconds},
        retries=note,
        recipe=first.recipe,
        seed=first.seed,
    )


def at_own_voxel(made: Any, feats: Features) -> bool:
    """Whether ``made`` (a :class:`~byoc_cli.pipeline.registrar.Registrar`) extracted
    ``feats`` at the features' own voxel: a voxel given, or an auto voxel that did not scale
    the clouds. The retries run only there: on the 14 simulated TLS rooms of docs/rooms.md,
    most brought to the features' scale by factors of 1.8 to 2.5, they changed no count and
    cost 42 % more CPU."""
    return not made.auto_voxel or math.isclose(feats.voxel_size, made.voxel_size)


def retried(made: Any, first: Registration, pair: tuple, settings: dict, recipe: Any):
    """:func:`with_retries` of ``first``, the result of ``made.match_alone`` on ``pair``
    (source and target :class:`Features`) with ``settings`` (its keywords), whose recipe is
    ``recipe``; each retry changes only the seed. No retries where :func:`at_own_voxel` is
    false."""
    gate = recipe.gate
    retries = gate.retries if at_own_voxel(made, pair[0]) else 0
    again = reseeded(made, pair, settings)
    return with_retries(first, again, recipe.seed, retries, gate.min_confidence)


def reseeded(made: Any, pair: tuple, settings: dict) -> Callable[[int], Registration]:
    """``again(seed)``: ``made.match_alone`` of ``pair`` (source and target
    :class:`Features`) with ``settings`` (its keywords) and only the seed changed (the
    retries' and the check's tries)."""
    src, tgt = pair

    def again(seed: int) -> Registration:
        return made.match_alone(src, tgt, **{**settings, "seed": seed})

    return again
