"""The sequence of one pair through the register engine (the stages:
:mod:`byoc_cli.pipeline.registrar`)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from byoc_cli.pipeline.feature_choice import (
    LEARNED_SECOND_OPINION,
    applies,
    features_for,
    smooth_first,
)
from byoc_cli.pipeline.local import InitialPose, LocalPair, check_global, register_local
from byoc_cli.pipeline.memo import InPlace, all_done
from byoc_cli.pipeline.results import Features, Registration
from byoc_cli.pipeline.turns import source_turner
from byoc_cli.threads import in_worker


def register_pair(
    made: Any, clouds: tuple[Any, Any], scale: float | None, load: dict, settings: dict
) -> Registration:
    """Register ``clouds`` (source, target: arrays or files) with ``made``, a
    :class:`~byoc_cli.pipeline.registrar.Registrar`: read and measure both side by side on its
    workers, choose the pair's voxel, extract both clouds' features and build their
    refinement levels side by side, then match, fit, refine and judge them
    (:meth:`~byoc_cli.pipeline.registrar.Registrar.match`).

    Args:
        scale: the inputs' factor to metres (None: see ``Featurizer.load``).
        load: ``intrinsics`` and ``depth_scale`` for depth-image files.
        settings: the keywords of ``Registrar.match``.

    With learned features, an auto voxel and the FPFH fallback, a pair of smooth clouds is
    registered with FPFH instead (:mod:`byoc_cli.pipeline.feature_choice`): the learned
    features are not extracted.

    Returns:
        the registration; its ``timings`` add ``load``, ``scale``, ``features_src``,
        ``features_tgt``, ``prepare_src``, ``prepare_tgt`` (when the learned features ran),
        ``first`` (when FPFH went first) and ``total`` (wall time).
    """
    start = time.perf_counter()
    refine = settings.get("refine") or made.recipe.refinement.method
    multiscale = refine == "multiscale"
    pool = InPlace() if in_worker() else made.executor()
    labels = ("source", "target")
    read = [
        pool.submit(_loaded, made, c, k, scale, load) for c, k in zip(clouds, labels, strict=True)
    ]
    (src_points, src_name, src_scale, t_src), (tgt_points, tgt_name, tgt_scale, t_tgt) = (
        job.result() for job in all_done(read)
    )
    t_scale = time.perf_counter()
    choice, voxels, picked = None, [(None, None, 1.0)] * 2, None
    if made.auto_voxel:
        choice = made.voxel_for(src_scale, tgt_scale)
        voxels = [(choice.voxel_size, choice.refine_voxel, choice.keep_of(k)) for k in (0, 1)]
        if applies(made):
            picked = features_for(
                made, (src_points, tgt_points), choice.voxel_size, (src_scale, tgt_scale)
            )
    t_choice = time.perf_counter() - t_scale
    steps: dict[str, float] = {}

    def learned(second_opinion: bool = True) -> Registration:
        """The learned pass: both clouds' features and refinement levels side by side, then
        :meth:`~byoc_cli.pipeline.registrar.Registrar.match`."""
        jobs = [
            pool.submit(
                _prepared_features,
                made,
                points,
                name,
                scale,
                voxels[k],
                multiscale and k == 0,
                multiscale and k == 1,
            )
            for k, (points, name) in enumerate(((src_points, src_name), (tgt_points, tgt_name)))
        ]
        (src, f_src), (tgt, f_tgt) = (job.result() for job in all_done(jobs))
        steps.update(features_src=f_src["features"], features_tgt=f_tgt["features"])
        steps.update(prepare_src=f_src["prepare"], prepare_tgt=f_tgt["prepare"])
        if not second_opinion:
            return pool.submit(made.match_alone, src, tgt, **settings).result()
        turned = source_turner(made, src, scale, src_name, voxels[0])
        return pool.submit(made.match, src, tgt, turned=turned, **settings).result()

    if picked is not None and picked.first == "fpfh":
        seed = settings.get("seed")
        clouds = (src_points, tgt_points)
        second = (lambda: learned(False)) if LEARNED_SECOND_OPINION else None
        result = smooth_first(made, clouds, [src_scale, tgt_scale], second, picked, scale, seed)
    else:
        result = learned()
        picked = None if picked is None else picked.as_dict()
        voxel_choice = None if choice is None else choice.as_dict()
        result = result._replace(features_choice=picked, voxel_choice=voxel_choice)
    timings = {
        "load": t_src["load"] + t_tgt["load"],
        "scale": t_src["scale"] + t_tgt["scale"] + t_choice,
        **steps,
        **result.timings,
        "total": time.perf_counter() - start,
    }
    if result.voxel_choice is None and choice is not None:  # the learned pass's (FPFH's: its own)
        result = result._replace(voxel_choice=choice.as_dict())
    return result._replace(timings=timings)


def register_either(
    made: Any, clouds: tuple[Any, Any], scale: float | None, load: dict, settings: dict, init
) -> Registration:
    """:func:`register_pair` without ``init``; with a ``(4, 4)`` guess of ``T_tgt_src`` (input
    units), :func:`register_from_init` of it, within ``settings``' ``max_correction``
    (``(degrees, distance in input units or None)``) in its ``init_mode`` (the rest of
    ``settings``: :meth:`~byoc_cli.pipeline.registrar.Registrar.match`'s keywords).

    Raises:
        ValueError: a bad ``init``, ``max_correction`` or ``init_mode``, or either of the
            latter without ``init`` (:meth:`~byoc_cli.pipeline.local.InitialPose.of`).
    """
    trust, mode = settings.pop("max_correction", None), settings.pop("init_mode", "local")
    if init is None and (trust is not None or mode != "local"):
        raise ValueError("max_correction and init_mode go with an init")
    if init is None:
        return register_pair(made, clouds, scale, load, settings)
    guess = InitialPose.of(init, trust, mode)
    return register_from_init(made, clouds, scale, load, settings, guess)


def register_from_init(
    made: Any, clouds: tuple[Any, Any], scale: float | None, load: dict, settings: dict, guess
) -> Registration:
    """Register ``clouds`` with ``made`` from ``guess``, an
    :class:`~byoc_cli.pipeline.local.InitialPose`: its ``mode`` ``"local"`` reads and
    measures both clouds, chooses the pair's voxel and runs the local registration
    (:func:`~byoc_cli.pipeline.local.register_local`); ``"global"`` runs
    :func:`register_pair` first and checks its result against the guess
    (:func:`~byoc_cli.pipeline.local.check_global`). Arguments as :func:`register_pair`'s.
    """
    found = register_pair(made, clouds, scale, load, settings) if guess.mode == "global" else None
    pair, timings = local_pair(made, clouds, scale, load)
    if found is None:
        return register_local(made, pair, guess.T, guess.trust, timings)
    return check_global(made, found, pair, guess, timings)


def local_pair(
    made: Any, clouds: tuple[Any, Any], scale: float | None, load: dict
) -> tuple[LocalPair, dict[str, float]]:
    """Both clouds read and measured side by side on ``made``'s workers, with the pair's
    refinement voxel (the auto choice's, else the registrar's voxel): the
    :class:`~byoc_cli.pipeline.local.LocalPair` and the seconds of ``load`` and ``scale``."""
    pool = InPlace() if in_worker() else made.executor()
    labels = ("source", "target")
    read = [
        pool.submit(_loaded, made, c, k, scale, load, False)
        for c, k in zip(clouds, labels, strict=True)
    ]
    (src, _, src_scale, t_src), (tgt, _, tgt_scale, t_tgt) = (
        job.result() for job in all_done(read)
    )
    start = time.perf_counter()
    voxel, choice = made.voxel_size, None
    if made.auto_voxel:
        choice = made.voxel_for(src_scale, tgt_scale)
        voxel = choice.refine_voxel
    timings = {
        "load": t_src["load"] + t_tgt["load"],
        "scale": t_src["scale"] + t_tgt["scale"] + time.perf_counter() - start,
    }
    factor = 1.0 if scale is None else float(scale)
    as_dict = None if choice is None else choice.as_dict()
    return LocalPair((src, tgt), voxel, factor, as_dict), timings


def _loaded(
    made: Any, cloud: Any, label: str, scale: float | None, load: dict, lines: bool = True
) -> tuple[np.ndarray, str, Any, dict[str, float]]:
    """Read one cloud and (auto voxel) measure it, its scan lines when ``lines``: ``(points,
    name, CloudScale | None, seconds of each step)``."""
    start = time.perf_counter()
    points, name = made.load(cloud, label, scale, **load)
    loaded = time.perf_counter()
    size = made.cloud_scale(points, name, lines) if made.auto_voxel else None
    return points, name, size, {"load": loaded - start, "scale": time.perf_counter() - loaded}


def _prepared_features(
    made: Any,
    points: np.ndarray,
    name: str,
    scale: float | None,
    voxel: tuple,
    as_source: bool,
    as_target: bool,
) -> tuple[Features, dict[str, float]]:
    """Extract one cloud's features at ``voxel`` (``(voxel_size, refine_voxel, keep)``)
    and prepare its refinement levels; the features and the seconds of each step."""
    start = time.perf_counter()
    feats = made.extract_points(points, scale, name, *voxel)
    extracted = time.perf_counter()
    if as_target:  # the finer (larger) levels to the next idle worker, the first here
        made.executor().submit(made.prepare_refinement, feats, as_source, True, (2, 1))
        made.prepare_refinement(feats, as_source, True, (0,))
    elif as_source:
        made.prepare_refinement(feats, True, False)
    done = time.perf_counter()
    return feats, {"features": extracted - start, "prepare": done - extracted}
