"""Which features a pair starts with, read from the clouds before any is extracted.

The learned features were trained on depth frames of rooms and desks: they match edges,
corners and clutter. Laser scans of smooth free-form objects (no table, curved surfaces) have
almost none, and there the learned pass fails where FPFH, run as the fallback below the gate,
registers the pair: such a pair paid for two registrations. At the pair's auto voxel
(:mod:`byoc_cli.pipeline.scale`) the share of a cloud's neighbourhoods that are not smooth
surfaces (:func:`~byoc_cli.geometry.sampling.rough_share`) tells them apart: 25 % to 94 % on
rooms, desks, 3DMatch fragments, LiDAR streets and scans of boxes on a table, at most 6 % on
the laser scans of smooth objects of ``benchmarks/objects.py`` (``docs/objects.md``). A
noise-free render of a room of plain boxes is smooth too: FPFH goes first there as well, with
the learned features below the gate.

When both clouds of a pair are smooth (at most :data:`SMOOTH_SHARE` rough), or the pair is an
object smaller than the trained size (:func:`~byoc_cli.pipeline.fallback.small_objects`: a
radius below 0.15 m, where range noise reads rough, or such an object in millimetres:
:func:`~byoc_cli.pipeline.scale.object_in_millimetres`), FPFH registers it (the fallback's preset
with the changes of :data:`SMOOTH_FPFH`) and the learned features are skipped
(:func:`smooth_first`). On the rough small objects of ``docs/objects.md`` (the tabletop box,
noisy laser scans) the learned features first registered 114 pairs right and passed 8 wrong,
FPFH first 113 and 6, in a third to a quarter of the time of those pairs: the learned pass
mostly fell below the gate there and the FPFH fallback ran after it.

Measured on the smooth pairs of ``benchmarks/objects.py`` (docs/objects.md): as FPFH's second
opinion below the gate the learned features registered none of 64 pairs that FPFH had not
(:data:`LEARNED_SECOND_OPINION` turns them back on); the refinement's restarts came back to the
result wherever its confidence before them was above 0.3 (on rooms they do not: a 3DLoMatch
result at 0.89 fell to 0.22), so they are left out; and 3000 points per cloud into matching
instead of FPFH's 10000 registered 64 of 96 pairs instead of 60, none wrong instead of 2, in
21 % less time. Anywhere else the learned features go first, as before. The report's
``features_choice`` says which went first and why.

FPFH's confidence on smooth surfaces is low for right and wrong results alike: a smooth
pair's result below the gate that two repeats (another seed, another estimator) reproduce
passes (:func:`reproduce`; measured in ``docs/objects.md``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np

from byoc_cli.errors import RegistrationError
from byoc_cli.pipeline.local import correction
from byoc_cli.pipeline.results import Registration

#: a pair whose clouds both have at most this share of rough neighbourhoods at its voxel
#: starts with FPFH (between the 6 % of smooth objects and the 25 % of a cabinet's frame)
SMOOTH_SHARE = 0.125
#: a smooth pair's learned features run as the second opinion when FPFH's confidence is
#: below the gate (False: skipped; measured in docs/objects.md)
LEARNED_SECOND_OPINION = False
#: a smooth pair's FPFH recipe: the ``fpfh`` preset changed so
#: (:meth:`~byoc_cli.pipeline.recipe.RegistrationRecipe.changed` paths)
SMOOTH_FPFH = (("refinement__restarts", False), ("matching__max_points", 3000))
#: a smooth pair's FPFH result below the gate whose refinement ends with a residual
#: (``cues["rmse"]``, in refinement voxels) at most this is fitted twice more
#: (:func:`reproduce`), at any confidence: on the smooth development sets the right results
#: that both repeats reproduce end at 0.19 to 0.24, the wrong ones (symmetric shapes turned
#: 100 to 180 deg) at 0.28 to 0.30, and no wrong result below 0.2 ends within it
REPRODUCE_RMSE = 0.25
#: the confidence of a result that both repeats reproduce (it then passes the default gate):
#: the 95 % lower bound (Wilson) of the share right among such results of the smooth
#: development sets when the rule was set, 22 of 22 (81 of 81 on the seven sets of
#: ``docs/objects.md`` now)
REPRODUCED_CONFIDENCE = 0.85
#: a repeat reproduces a result when it lands within these degrees and these FPFH voxels (at
#: the source's centroid) of it
AGREE_DEG = 2.0
AGREE_VOXELS = 2.0
#: the repeats: a name, the seed's offset from the pair's, and the changes to
#: :data:`SMOOTH_FPFH` (the next seed's RANSAC; the ``sc2`` estimator on the same matches)
REPEATS = (("next seed", 1, ()), ("sc2", 0, (("fitting__estimator", "sc2"),)))
#: an object below the trained size whose FPFH result stays below the gate (repeats and all)
#: is registered again with FPFH features at these many times the auto voxel, in turn, until
#: one result is kept (the refinement's voxel as it is): coarser histograms see more of a
#: noisy surface's shape
COARSER = (1.4, 2.0)
#: such a result is kept when it passes the gate and its refinement ends with a residual
#: (``cues["rmse"]``, in refinement voxels) at most this: on the development sets the wrong
#: results that passed ended at 0.244 to 0.336 (x 1.4) and 0.242 to 0.349 (x 2), mostly
#: symmetric shapes turned onto themselves; the right ones at 0.184 to 0.292
COARSER_RMSE = 0.24


class FeaturesChoice(NamedTuple):
    """Which features a pair starts with and why.

    Attributes:
        first: ``"byoc"`` or ``"fpfh"``.
        rough_share: per cloud, the share of its neighbourhoods that are not smooth surfaces
            at the pair's voxel (:func:`~byoc_cli.geometry.sampling.rough_share`).
        reason: one sentence for reports and logs.
        small_object: the pair is smaller than the trained size (FPFH first, rough or not).
        in_millimetres: it is so read as an object in millimetres
            (:func:`~byoc_cli.pipeline.scale.object_in_millimetres`).
    """

    first: str
    rough_share: tuple[float, ...]
    reason: str
    small_object: bool = False
    in_millimetres: bool = False

    def as_dict(self) -> dict:
        """JSON-ready: ``first``, ``rough_share``, ``smooth_share`` (the threshold),
        ``small_object``, ``in_millimetres``, ``reason``."""
        return {
            "first": self.first,
            "rough_share": list(self.rough_share),
            "smooth_share": SMOOTH_SHARE,
            "small_object": self.small_object,
            "in_millimetres": self.in_millimetres,
            "reason": self.reason,
        }


def choose_features(
    rough: Sequence[float], small: bool = False, millimetres: bool = False
) -> FeaturesChoice:
    """The features a pair whose clouds have ``rough`` shares of rough neighbourhoods starts
    with: ``"fpfh"`` when every one is at most :data:`SMOOTH_SHARE` or the pair is ``small``
    (smaller than the trained size; ``millimetres``: read so as an object in millimetres),
    else ``"byoc"``. A ``small`` pair needs no shares (``rough`` empty: not measured)."""
    rough = tuple(float(r) for r in rough)
    shares = ", ".join(f"{100 * r:.0f} %" for r in rough)
    recipe = "FPFH features (3000 points, no restarts)"
    if small and not rough:
        unit = ", read as millimetres (seen from outside, not a panorama)" if millimetres else ""
        why = f"an object below the trained size{unit}: {recipe}"
        return FeaturesChoice("fpfh", rough, why, True, millimetres)
    if max(rough) <= SMOOTH_SHARE:
        why = (
            f"smooth surfaces ({shares} of the neighbourhoods rough, at most "
            f"{100 * SMOOTH_SHARE:g} %): {recipe}"
        )
        return FeaturesChoice("fpfh", rough, why, small)
    if small:
        why = f"an object below the trained size ({shares} of the neighbourhoods rough): {recipe}"
        return FeaturesChoice("fpfh", rough, why, True)
    why = f"edges and clutter ({shares} of the neighbourhoods rough): the learned features first"
    return FeaturesChoice("byoc", rough, why)


def applies(made: Any) -> bool:
    """Whether a registrar ``made`` chooses the features per pair: learned features with an
    auto voxel and the FPFH fallback (``--fallback none`` or a voxel given keeps them)."""
    return made.features == "byoc" and made.auto_voxel and made.fallback == "fpfh"


def features_for(
    made: Any, clouds: Sequence[np.ndarray], voxel_size: float, scales: Sequence
) -> FeaturesChoice:
    """:func:`choose_features` of the ``clouds`` (``(N, 3)`` arrays in metres) at the pair's
    ``voxel_size``, each cloud's share measured once per voxel by ``made``
    (:meth:`~byoc_cli.pipeline.featurizer.Featurizer.rough_share`), small when their
    :class:`~byoc_cli.pipeline.scale.CloudScale` ``scales`` are
    (:func:`~byoc_cli.pipeline.fallback.small_objects`). A small pair starts with FPFH
    whatever its shares, so they are not measured (about a tenth of such a pair's time)."""
    from byoc_cli.pipeline.fallback import small_objects
    from byoc_cli.pipeline.scale import object_in_millimetres

    if small_objects(scales):
        return choose_features((), small=True, millimetres=object_in_millimetres(tuple(scales)))
    rough = [made.rough_share(points, voxel_size) for points in clouds]
    return choose_features(rough)


def smooth_first(
    made: Any,
    clouds: tuple[np.ndarray, np.ndarray],
    scales: list,
    learned: Callable[[], Registration] | None,
    choice: FeaturesChoice,
    scale: float | None,
    seed: int | None = None,
) -> Registration:
    """FPFH for a smooth pair (its recipe changed by :data:`SMOOTH_FPFH`), the learned
    features as the second opinion when asked.

    Args:
        made: the learned :class:`~byoc_cli.pipeline.registrar.Registrar` (its fallback's
            registrar runs FPFH, its gate decides).
        clouds: source and target ``(N, 3)`` in metres.
        scales: their :class:`~byoc_cli.pipeline.scale.CloudScale`.
        learned: the learned registration of the pair without its own fallback, called only
            when FPFH's confidence is below the gate; None: never.
        choice: the :class:`FeaturesChoice` that sent the pair here (the report's).
        scale: the factor the learned registration's translation is in (the target's
            factor to metres; None: 1): FPFH's is divided by it.
        seed: seeds FPFH's random choices (None: the recipe's).

    Returns:
        FPFH's registration when it passes the gate or no ``learned`` is given; else the
        more confident of the two. ``features_choice`` says why FPFH went first;
        ``fallback`` (when the learned features ran) says what they reached;
        ``timings["first"]`` holds FPFH's seconds; ``passed`` is by ``made``'s gate.

    Raises:
        RegistrationError: neither could register the pair.
    """
    start = time.perf_counter()
    repeat = made.recipe.seed if seed is None else seed
    units = 1.0 if scale is None else scale

    def fit(factor: float, offset: int, changes: tuple) -> Registration:
        """FPFH at ``factor`` times the auto voxel, the seed ``offset`` on (T in metres)."""
        seed_of = (repeat + offset) % 2**64
        return made.fpfh_registration(clouds, scales, seed_of, SMOOTH_FPFH + changes, factor)

    try:
        first = in_units(fit(1.0, 0, ()), units)
    except RegistrationError:
        if learned is None:
            raise
        first = None
    seconds = time.perf_counter() - start
    picked = choice.as_dict()
    gate = made.fallback_below
    if first is not None and worth_repeating(first, gate):
        first = reproduce(first, lambda o, c: fit(1.0, o, c), clouds[0].mean(axis=0), units)
    if first is not None and choice.small_object and first.confidence < gate:
        first, picked["coarser"] = retry_coarser(first, fit, gate, clouds[0].mean(axis=0), units)
    if first is not None and (learned is None or first.confidence >= made.fallback_below):
        timings = {**first.timings, "first": seconds}
        passed = first.confidence >= made.fallback_below
        return first._replace(timings=timings, features_choice=picked, passed=passed)
    second_start = time.perf_counter()
    second = learned()  # raises when it cannot register either (and FPFH could not)
    used = first is None or second.confidence > first.confidence
    note = {
        "features": "byoc",
        "used": used,
        "first_confidence": None if first is None else first.confidence,
        "confidence": second.confidence,
        "seconds": time.perf_counter() - second_start,
    }
    kept = second if used else first
    timings = {**kept.timings, "first": seconds}
    passed = kept.confidence >= made.fallback_below
    return kept._replace(timings=timings, fallback=note, features_choice=picked, passed=passed)


def retry_coarser(
    first: Registration,
    fit: Callable[[float, int, tuple], Registration],
    gate: float,
    centroid: np.ndarray,
    scale: float = 1.0,
) -> tuple[Registration, dict]:
    """An object's FPFH result ``first`` below the ``gate``, and the registrations of the same
    pair with FPFH features at each factor of :data:`COARSER` in turn (each with its repeats,
    :func:`reproduce`, where :func:`worth_repeating`): the first of them that passes the gate
    with a residual at most :data:`COARSER_RMSE`, else ``first``.

    Args:
        first: the FPFH registration at the auto voxel, ``T_tgt_src`` in the input's units
            (times ``scale``: metres).
        fit: ``fit(factor, seed_offset, changes)`` registers the pair with features at
            ``factor`` times the auto voxel (T in metres), raising
            :class:`~byoc_cli.errors.RegistrationError` when it cannot.
        gate: the confidence a result passes at.
        centroid: ``(3,)`` the source's centroid in metres (for the repeats).
        scale: the factor ``first``'s translation was divided by (metres to its units).

    Returns:
        ``(kept, note)``: the kept registration (``timings["coarser"]``: the tries' seconds)
        and the report's ``features_choice.coarser``: ``first_confidence`` (``first``'s),
        ``used`` (the factor of the kept try, None for none) and ``tries``, one per factor
        tried: ``factor``, ``voxel_size`` (metres), ``confidence`` and ``rmse`` (None where
        FPFH could not register the pair).
    """
    start = time.perf_counter()
    kept, tries = first, []
    for factor in COARSER:
        again = _coarser_try(factor, fit, gate, centroid, scale)
        rmse = None if again is None else (again.cues or {}).get("rmse", float("inf"))
        tries.append(
            {
                "factor": factor,
                "voxel_size": None if again is None else again.voxel_size,
                "confidence": None if again is None else again.confidence,
                "rmse": rmse,
            }
        )
        if again is not None and again.confidence >= gate and rmse <= COARSER_RMSE:
            kept = again
            break
    note = {
        "first_confidence": first.confidence,
        "used": tries[-1]["factor"] if kept is not first else None,
        "tries": tries,
    }
    return kept._replace(timings={**kept.timings, "coarser": time.perf_counter() - start}), note


def _coarser_try(factor, fit, gate, centroid, scale) -> Registration | None:
    """One try of :func:`retry_coarser` at ``factor`` (T in the input's units), None where
    FPFH cannot register the pair."""
    try:
        again = fit(factor, 0, ())
    except RegistrationError:
        return None
    again = in_units(again, scale)
    if worth_repeating(again, gate):
        again = reproduce(
            again, lambda offset, changes: fit(factor, offset, changes), centroid, scale
        )
    return again


def in_units(result: Registration, scale: float) -> Registration:
    """``result`` (T in metres) with its translation divided by ``scale`` (metres to the
    input's units)."""
    T = result.T_tgt_src.copy()
    T[:3, 3] /= scale
    return result._replace(T_tgt_src=T)


def worth_repeating(first: Registration, gate: float) -> bool:
    """Whether ``first`` (FPFH's result of a smooth pair, or the fallback's of an object) is
    below the ``gate`` and the repeats could raise it: its residual is at most
    :data:`REPRODUCE_RMSE`."""
    rmse = (first.cues or {}).get("rmse", float("inf"))
    return first.confidence < gate and rmse <= REPRODUCE_RMSE


def reproduce(
    first: Registration,
    fit: Callable[[int, tuple], Registration],
    centroid: np.ndarray,
    scale: float = 1.0,
) -> Registration:
    """An FPFH result below the gate (a smooth pair's, or the fallback's of objects below the
    trained size: :meth:`~byoc_cli.pipeline.fallback.Fallback.second_opinion`), fitted twice
    more (:data:`REPEATS`).

    On smooth surfaces FPFH's confidence is low for right and wrong results alike
    (``docs/objects.md``): of its results below the gate on the smooth development sets,
    most right ones land again where they are under another seed and another estimator, most
    wrong ones elsewhere; the wrong ones that land again (symmetric shapes) end with a larger
    residual, above :data:`REPRODUCE_RMSE` (checked before this runs). A result that both
    repeats reproduce (within :data:`AGREE_DEG` and :data:`AGREE_VOXELS` at the source's
    centroid) takes :data:`REPRODUCED_CONFIDENCE` when that is higher; the others keep theirs.

    Args:
        first: FPFH's registration of the pair, ``T_tgt_src`` in the input's units (times
            ``scale``: metres).
        fit: ``fit(seed_offset, changes)`` registers the pair again (T in metres), raising
            :class:`~byoc_cli.errors.RegistrationError` when it cannot.
        centroid: ``(3,)`` the source's centroid in metres.
        scale: the factor ``first``'s translation was divided by (metres to its units).

    Returns:
        ``first`` with ``reproduced`` (``repeats``: each one's ``name``, ``degrees``,
        ``shift`` (metres) and ``confidence``, None where it could not register; ``agree``;
        ``model_confidence``: the confidence before) and ``timings["reproduce"]``, and the
        confidence above when both agree.
    """
    start = time.perf_counter()
    T_first = first.T_tgt_src.copy()
    T_first[:3, 3] *= scale  # metres, as the repeats'
    tolerance = AGREE_VOXELS * first.voxel_size  # FPFH's voxel, in metres
    repeats, agree = [], True
    for name, offset, changes in REPEATS:
        try:
            again = fit(offset, changes)
        except RegistrationError:
            repeats.append({"name": name, "degrees": None, "shift": None, "confidence": None})
            agree = False
            continue
        degrees, shift = correction(again.T_tgt_src, T_first, centroid)
        repeats.append(
            {"name": name, "degrees": degrees, "shift": shift, "confidence": again.confidence}
        )
        agree = agree and degrees <= AGREE_DEG and shift <= tolerance
    note = {"repeats": repeats, "agree": agree, "model_confidence": first.confidence}
    confidence = max(first.confidence, REPRODUCED_CONFIDENCE) if agree else first.confidence
    timings = {**first.timings, "reproduce": time.perf_counter() - start}
    return first._replace(confidence=confidence, reproduced=note, timings=timings)
