"""The judgement's second opinion: when the learned features' registration of a pair is
below the gate, the same clouds are registered again with FPFH features (refined the same
way) and the more confident result is kept; the result's ``fallback`` says what ran.

FPFH sizes its voxel by the scene (:func:`~byoc_cli.pipeline.scale.size_radius`): on a laser
scan, whose points crowd around the scanner, that is coarser than the learned features' own.
On panoramas that large FPFH's result is checked against its turns about the up axis
(:mod:`~byoc_cli.pipeline.structure_check`), and where they are rooms (laser scans of rooms:
:func:`large_panoramas`) every result, the learned features' too: a room turned 90 or 180
deg fits its floor, ceiling and walls, and no confidence tells it; a turn that fits what
stands in the room clearly better is taken instead. On the 14 simulated rooms of
docs/rooms.md this takes FPFH's voxel from 5-13 cm to 11-16 cm and the default from 6 right
and 2 wrong with exit 0 to 10 and 0.

On objects smaller than the trained size (:func:`small_objects`: laser scans of objects of
10 to 30 cm, in metres, or in millimetres seen from outside) the learned features often
match nothing and FPFH registers the pair below the gate; a result with a small residual is
then fitted twice more, as a smooth pair's (:func:`~byoc_cli.pipeline.feature_choice.reproduce`),
and passes when both repeats land on it. ``register`` and ``register-batch`` start such pairs
with FPFH (:mod:`~byoc_cli.pipeline.feature_choice`); this serves where the learned features went
first all the same (:meth:`~byoc_cli.pipeline.registrar.Registrar.match` on features
extracted apart). Depth frames and fragments, which are within the trained size, are not
repeated: on a camera circling a cabinet the repeats land again on a pose near the identity
(the frame's own pattern matched to itself) as readily as on the truth; nor are other scans
larger than it (LiDAR sampled along rings, a pattern of its own; panoramas; objects in
millimetres that :func:`~byoc_cli.pipeline.scale.object_in_millimetres` does not pick).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from byoc_cli.errors import RegistrationError
from byoc_cli.pipeline.results import Features, Registration

#: the fallback's recipe changes on scans larger than the trained range (FPFH's size): the
#: structure check of its result (``matching.turns``: FPFH tries no turned sources)
LARGE_SCANS = (("matching__turns", True),)
#: recipe changes that :meth:`~byoc_cli.pipeline.registrar.Registrar.match` takes per call
#: (its keywords): registrations that differ only in these (a result and its ``sc2`` repeat)
#: share one registrar, and so the features of their clouds
PER_CALL = {"fitting__estimator": "estimator"}


class Fallback:
    """The FPFH registrar of a learned one, made on first use.

    Args:
        voxel_size: ``"auto"``, or the FPFH voxel in metres (twice the learned one: the
            features' reference voxels are 5 cm and 2.5 cm).
        turns: the learned registrar's ``matching.turns``: FPFH's recipe carries True, so
            that its results are checked against their turns about the up axis as the learned
            ones are (:meth:`~byoc_cli.pipeline.solve.Solver.check_structure`; FPFH tries
            no turned sources); ``"auto"`` carries nothing: no structure check.
    """

    def __init__(self, voxel_size: float | str, turns: bool | str = False) -> None:
        self.voxel_size = voxel_size
        self.turns = turns
        self._registrars: dict[tuple, Any] = {}
        self._lock = threading.Lock()

    def registrar(self, changes: tuple[tuple[str, Any], ...] = ()):
        """The FPFH :class:`~byoc_cli.pipeline.registrar.Registrar` (one thread) of the
        ``fpfh`` preset (with :attr:`turns`), with ``changes`` (``(path, value)`` pairs of
        :meth:`~byoc_cli.pipeline.recipe.RegistrationRecipe.changed`: a smooth pair's,
        :data:`byoc_cli.pipeline.feature_choice.SMOOTH_FPFH`)."""
        from byoc_cli.pipeline.recipe import preset
        from byoc_cli.pipeline.registrar import Registrar

        with self._lock:
            if changes not in self._registrars:
                turns = True if self.turns is True else None  # None: the preset's
                recipe = preset("fpfh").changed(**{"matching__turns": turns, **dict(changes)})
                self._registrars[changes] = Registrar(
                    "fpfh", voxel_size=self.voxel_size, threads=1, recipe=recipe
                )
            return self._registrars[changes]

    def second_opinion(
        self, learned: Any, first: Registration, src: Features, tgt: Features, seed: int
    ) -> Registration:
        """``first`` (a registration by ``learned``, below its gate) or, when more confident,
        the FPFH registration of the same clouds (``src.cloud``, ``tgt.cloud``); the kept
        result's ``fallback`` and ``timings["fallback"]`` say what ran, and its ``retries``
        what ``first``'s did. Without both clouds: ``first`` as it is."""
        if src.cloud is None or tgt.cloud is None:
            return first
        start = time.perf_counter()
        try:
            scales, changes = None, ()
            if self.registrar().auto_voxel:  # the scales the learned choice read
                scales = [
                    learned.cloud_scale(f.cloud, label)
                    for f, label in ((src, "source"), (tgt, "target"))
                ]
                changes = changes_for(scales)
            second = self.register((src.cloud, tgt.cloud), scales, seed, changes)
        except RegistrationError:
            second = None
        seconds = time.perf_counter() - start
        used = second is not None and second.confidence > first.confidence
        note = {
            "features": "fpfh",
            "used": used,
            "learned_confidence": first.confidence,
            "confidence": None if second is None else second.confidence,
            "voxel_choice": None if second is None else second.voxel_choice,
            "seconds": seconds,
        }
        timings = {**first.timings, "fallback": seconds}
        if not used:
            return first._replace(timings=timings, fallback=note)
        if scales is not None and small_objects(scales):
            how = (seed, changes, scales)
            second = self._repeated(second, learned.fallback_below, src, tgt, how)
        T = second.T_tgt_src.copy()
        T[:3, 3] /= src.scale
        return second._replace(T_tgt_src=T, timings=timings, fallback=note, retries=first.retries)

    def _repeated(
        self, second: Registration, gate: float, src: Features, tgt: Features, how: tuple
    ) -> Registration:
        """``second`` (FPFH's registration, T in metres) with its repeats
        (:func:`~byoc_cli.pipeline.feature_choice.reproduce`) when it is below ``gate`` with a
        small residual (:func:`~byoc_cli.pipeline.feature_choice.worth_repeating`); ``how``:
        the ``(seed, changes, scales)`` it was registered with."""
        from byoc_cli.pipeline.feature_choice import reproduce, worth_repeating

        if not worth_repeating(second, gate):
            return second
        seed, changes, scales = how
        clouds = (src.cloud, tgt.cloud)
        return reproduce(
            second,
            lambda offset, more: self.register(
                clouds, scales, (seed + offset) % 2**64, changes + more
            ),
            np.asarray(src.cloud).mean(axis=0),
        )

    def register(
        self,
        clouds: tuple[np.ndarray, np.ndarray],
        scales: list,
        seed: int,
        changes: tuple[tuple[str, Any], ...] = (),
        coarser: float = 1.0,
    ) -> Registration:
        """FPFH's registration of ``clouds`` (``(N, 3)`` in metres), refined by the multiscale
        ICP, from the :class:`~byoc_cli.pipeline.scale.CloudScale` ``scales`` that the learned
        registrar measured (read only with an auto voxel; None otherwise), by the registrar of
        ``changes`` (:meth:`registrar`), its features at ``coarser`` times the auto voxel (the
        refinement's voxel as it is); T in metres.

        Raises:
            RegistrationError: FPFH cannot register them.
        """
        kept = tuple((path, value) for path, value in changes if path not in PER_CALL)
        settings = {PER_CALL[path]: value for path, value in changes if path in PER_CALL}
        fpfh = self.registrar(kept)
        scales = scales if fpfh.auto_voxel else None
        return register_clouds(
            fpfh, clouds, scales, coarser, refine="multiscale", seed=seed, **settings
        )


def changes_for(scales: list) -> tuple[tuple[str, Any], ...]:
    """The fallback's recipe changes for clouds of the
    :class:`~byoc_cli.pipeline.scale.CloudScale` ``scales``: :data:`LARGE_SCANS` for
    panoramas (a cloud with an ``even_radius``: laser scans of rooms in their scanner's frame)
    that FPFH sizes above the trained range (:func:`~byoc_cli.pipeline.scale.size_radius`),
    none otherwise (the structure check was measured on rooms)."""
    from byoc_cli.pipeline.scale import TRAINED_RADIUS, size_radius  # torch: not on import

    panorama = any(s.even_radius is not None for s in scales)
    return LARGE_SCANS if panorama and size_radius(tuple(scales)) > TRAINED_RADIUS[1] else ()


def small_objects(scales: Sequence) -> bool:
    """Whether clouds of the :class:`~byoc_cli.pipeline.scale.CloudScale` ``scales`` are
    smaller than the trained size: their size (:func:`~byoc_cli.pipeline.scale.size_radius`)
    lies below :data:`~byoc_cli.pipeline.scale.TRAINED_RADIUS` (objects of 10 to 30 cm in
    metres; depth frames and fragments lie within it, rooms and LiDAR above it), or they read
    as such an object in millimetres
    (:func:`~byoc_cli.pipeline.scale.object_in_millimetres`), so that the same scan takes
    the same path in either unit."""
    from byoc_cli.pipeline.scale import (  # torch: not on import
        TRAINED_RADIUS,
        object_in_millimetres,
        size_radius,
    )

    scales = tuple(scales)
    return size_radius(scales) < TRAINED_RADIUS[0] or object_in_millimetres(scales)


def large_panoramas(made: Any, src: Features, tgt: Features) -> bool:
    """Whether ``made`` (a :class:`~byoc_cli.pipeline.featurizer.Featurizer` with an auto
    voxel) measured the clouds of ``src`` and ``tgt`` as panoramas larger than the trained
    range (:func:`changes_for`): laser scans of rooms, whose results the structure check turns
    back where the clouds are rooms
    (:attr:`~byoc_cli.pipeline.register.RegisterConfig.turn_rooms`). False without an auto
    voxel or both clouds, or where a cloud has too few points to measure."""
    if not made.auto_voxel or src.cloud is None or tgt.cloud is None:
        return False
    try:
        scales = [made.cloud_scale(f.cloud, k) for f, k in ((src, "source"), (tgt, "target"))]
    except RegistrationError:
        return False
    return bool(changes_for(scales))


def register_clouds(
    registrar: Any,
    clouds: tuple[np.ndarray, np.ndarray],
    scales: list | None,
    coarser: float = 1.0,
    **settings: Any,
) -> Registration:
    """What ``registrar.register`` gives for two arrays already in metres (``scale=1.0``),
    from their measured ``scales`` (auto voxel; :class:`~byoc_cli.pipeline.scale.CloudScale`,
    labelled ``"source"`` and ``"target"``) and the features of each array at its voxel
    computed once while among the most recent (a fallback registers the same clouds in many
    pairs of a batch); the same result, bytes and all. ``coarser``: the features' voxel is
    this many times the auto voxel (the refinement's stays; only with an auto voxel).
    ``settings``: the keywords of :meth:`~byoc_cli.pipeline.registrar.Registrar.match`."""
    start = time.perf_counter()
    names = ("source", "target")
    choice, voxels = None, [(None, None, 1.0)] * 2
    if registrar.auto_voxel:
        for points, scale in zip(clouds, scales, strict=True):  # measured: kept for match
            registrar.remember_scale(points, scale)
        choice = registrar.voxel_for(*scales)
        if coarser != 1.0:
            choice = choice._replace(voxel_size=choice.voxel_size * coarser)
        voxels = [(choice.voxel_size, choice.refine_voxel, choice.keep_of(k)) for k in (0, 1)]
    src, tgt = (
        registrar.features_at(points, names[k], voxels[k]) for k, points in enumerate(clouds)
    )
    result = registrar.match(src, tgt, **settings)
    return result._replace(
        timings={**result.timings, "total": time.perf_counter() - start},
        voxel_choice=None if choice is None else choice.as_dict(),
    )
