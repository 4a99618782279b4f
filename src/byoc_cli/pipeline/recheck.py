"""A second seed for a learned result that passes at low overlap: one pose, or two.

Where a small share of the two scans overlaps, the learned correspondences hold a few inliers
in a hundred, and the pose RANSAC settles on depends on the seed. A right pose comes back
under another seed; a pose that passed by chance, or one of two places the source fits
(kitchen cabinets side by side), often does not. So a learned result that passes the gate
with an estimated overlap below :data:`BELOW_OVERLAP` is matched, fitted and refined once more
with the next unused seed (the features are not extracted again). When that check ends
elsewhere (more than :data:`~byoc_cli.pipeline.turns.SAME_DEG` deg or
:data:`~byoc_cli.pipeline.turns.SAME_VOXELS` voxels away) at a confidence of at least
:data:`RIVAL_FLOOR`, the result is ambiguous: it does not pass (``byoc register`` exits 3) and
the report lists both poses. A check below the floor found no pose at all and is no rival.

On the 96 cut pairs of ``benchmarks/cut_pairs.py`` (12-32 % overlap, docs/low-overlap.md),
whole runs with seeds 1 and 2 reproduce 38 of the 41 right results of seed 0 that passed,
and 4 of its 10 wrong ones.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from byoc_cli.errors import RegistrationError
from byoc_cli.pipeline.retries import at_own_voxel, discounted, reseeded, retry_seed

if TYPE_CHECKING:  # numpy stays unloaded for the commands' --help, which reads the constants
    import numpy as np

    from byoc_cli.pipeline.results import Features, Registration

#: a passing learned result is checked when its estimated overlap is below this
BELOW_OVERLAP = 0.5
#: a check that ends elsewhere makes the result ambiguous from this model confidence on
RIVAL_FLOOR = 0.2


def needs_check(result: Registration, recheck: bool) -> bool:
    """Whether ``result`` is checked: ``recheck`` is on, the result passed, is the learned
    features' (not FPFH's), from their global path, with an overlap below
    :data:`BELOW_OVERLAP`."""
    return (
        recheck
        and result.passed
        and result.features == "byoc"
        and result.path == "global"
        and result.overlap < BELOW_OVERLAP
    )


def check_seed(result: Registration, seed: int) -> int:
    """The first seed ``result`` (of a run seeded ``seed``) did not use: after its retries."""
    tries = len((result.retries or {}).get("tries", ()))
    return retry_seed(seed, tries + 1)


def with_check(
    result: Registration,
    again: Callable[[int], Registration],
    seed: int,
    apart: Callable[[np.ndarray, np.ndarray], dict],
) -> Registration:
    """``result`` checked by ``again(seed)`` (the same registration of the same features
    with ``seed``): ambiguous when the check ends elsewhere at a model confidence of at least
    :data:`RIVAL_FLOOR`.

    Args:
        result: a result that :func:`needs_check`.
        again: registers the pair's features again with a seed.
        seed: the check's seed (:func:`check_seed`).
        apart: how far apart two ``(4, 4)`` poses put the source: ``rotation_deg``,
            ``translation`` (input units) and ``voxels`` (the translation in voxels).

    Returns:
        ``result``, or (ambiguous and the check more confident after the
        :func:`~byoc_cli.pipeline.retries.discounted` confidence of two tries) the check's
        pose; its ``check`` holds the check's ``seed``, ``model_confidence`` and
        ``T_tgt_src``, how far ``apart`` the two poses are, whether the check ``agrees``,
        whether the result is ``ambiguous`` (then it does not pass), the ``alternatives``
        (both poses, most confident first, each with ``seed``, ``confidence`` and
        ``T_tgt_src``), the ``kept_seed`` and the ``seconds``; ``timings["check"]`` the
        seconds. A check that raises ``RegistrationError`` is no rival (its ``error`` says why,
        ``T_tgt_src`` and ``apart`` are None).
    """
    from byoc_cli.pipeline.turns import SAME_DEG, SAME_VOXELS

    start = time.perf_counter()
    try:
        other = again(seed)
    except RegistrationError as exc:  # no transform under this seed: no rival either
        note = {"seed": seed, "model_confidence": 0.0, "T_tgt_src": None, "apart": None}
        note.update(agrees=False, ambiguous=False, alternatives=[], kept_seed=result.seed)
        note.update(seconds=time.perf_counter() - start, error=str(exc))
        return result._replace(check=note, timings={**result.timings, "check": note["seconds"]})
    gap = apart(other.T_tgt_src, result.T_tgt_src)
    agrees = gap["rotation_deg"] < SAME_DEG and gap["voxels"] < SAME_VOXELS
    ambiguous = not agrees and other.confidence >= RIVAL_FLOOR
    rival = other._replace(confidence=discounted(other.confidence, 2))
    kept = rival if ambiguous and rival.confidence > result.confidence else result
    poses = sorted((result, rival), key=lambda r: -r.confidence) if ambiguous else []
    seconds = time.perf_counter() - start
    note = {
        "seed": other.seed,
        "model_confidence": other.confidence,
        "T_tgt_src": other.T_tgt_src.tolist(),
        "apart": gap,
        "agrees": agrees,
        "ambiguous": ambiguous,
        "alternatives": [
            {"seed": r.seed, "confidence": r.confidence, "T_tgt_src": r.T_tgt_src.tolist()}
            for r in poses
        ],
        "kept_seed": kept.seed,
        "seconds": seconds,
    }
    return kept._replace(
        passed=result.passed and not ambiguous,
        check=note,
        timings={**kept.timings, "check": seconds},
        retries=result.retries,
        recipe=result.recipe,
        seed=result.seed,
    )


def checked(made: Any, result: Registration, pair: tuple, settings: dict, recipe: Any):
    """:func:`with_check` of ``result``, the learned result of ``made.match_alone`` (a
    :class:`~byoc_cli.pipeline.registrar.Registrar`) on ``pair`` (source and target
    :class:`Features`) with ``settings`` (its keywords), whose recipe is ``recipe``, where it
    :func:`needs_check` and the features are at their own voxel
    (:func:`~byoc_cli.pipeline.retries.at_own_voxel`); ``result`` otherwise."""
    src = pair[0]
    if not needs_check(result, recipe.gate.recheck) or not at_own_voxel(made, src):
        return result
    again = reseeded(made, pair, settings)
    return with_check(result, again, check_seed(result, recipe.seed), measure(src, result))


def measure(src: Features, result: Registration) -> Callable[[np.ndarray, np.ndarray], dict]:
    """``apart(T_a, T_b)`` for :func:`with_check`: the rotation between two poses and how far
    apart they put the source's median point (input coordinates and units; the translations
    of georeferenced scans differ by kilometres for 0.1 deg, and a stray point would drag a
    mean), in ``result``'s voxels too."""
    import numpy as np

    from byoc_cli.pipeline.local import correction

    points = src.cloud if src.cloud is not None else src.points
    at = np.median(points, axis=0) / src.scale
    voxel = result.voxel_size / src.scale

    def apart(T_a: np.ndarray, T_b: np.ndarray) -> dict:
        gap = correction(T_a, T_b, at)
        return {
            "rotation_deg": float(gap.rotation_deg),
            "translation": float(gap.translation),
            "voxels": float(gap.translation / voxel),
        }

    return apart
