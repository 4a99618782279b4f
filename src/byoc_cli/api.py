"""The Python API: the pipeline of ``byoc register`` with numpy in and out.

``from byoc_cli import register, extract_features, load_weights, load_cloud, Registrar``.
The functions take ``(N, 3)`` arrays (metres) or file paths, use the same recipe as the CLI
(:data:`byoc_cli.pipeline.recipe.PRESETS`, or a ``recipe=``) and give the same results
for the same seed: the ``byoc register``, ``register-batch`` and ``features`` commands are
built on them. Results are NamedTuples of numpy arrays and numbers. Errors are the typed
errors of :mod:`byoc_cli.errors`.

torch and the encoder are imported when a function is first called, not on import.

Threads: importing this module before torch is imported applies the tool's thread policy
(:mod:`byoc_cli.threads`): it puts ``OMP_WAIT_POLICY=PASSIVE`` and ``OMP_NUM_THREADS`` (the
cores the process may use: affinity and cgroup quota) into ``os.environ`` unless they are
set, so that torch starts with them. When torch is already imported nothing is changed.
A :class:`Registrar` runs its work on ``threads`` worker threads (default: torch's thread
count) with one torch thread each: the two clouds of a pair are read, encoded and
prepared side by side, and :meth:`Registrar.executor` lets callers run pairs side by side.
"""

from __future__ import annotations

import os
import sys
import threading
import time
import warnings
from collections import OrderedDict
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from byoc_cli.pipeline.recipe import RegistrationRecipe
    from byoc_cli.pipeline.weights import LoadedWeights

from byoc_cli.api_types import (
    DEPTH_EXTENSIONS,
    Features,
    Registration,
    _as_points,
    load_cloud,
    load_weights,
)
from byoc_cli.errors import RegistrationError
from byoc_cli.threads import apply_thread_policy, in_worker, side_by_side

if "torch" not in sys.modules:  # only before torch: OpenMP reads its settings when loaded
    apply_thread_policy()

__all__ = [
    "DEPTH_EXTENSIONS",
    "Features",
    "Registrar",
    "Registration",
    "extract_features",
    "load_cloud",
    "load_weights",
    "register",
]


class _FromRecipe:
    """The default of an argument that the recipe gives."""

    def __repr__(self) -> str:
        return "<the recipe's>"


_RECIPE: Any = _FromRecipe()


def _registrar_recipe(
    recipe: RegistrationRecipe | None,
    features: str | None,
    weights: Any,
    voxel_size: Any,
    fallback: str | None,
    fallback_below: float | None,
) -> RegistrationRecipe:
    """The recipe of a :class:`Registrar`: ``recipe`` (or the preset of ``features``) changed
    by the arguments that were given.

    Raises:
        ValueError: an unknown feature type, or a fallback that does not go with it.
    """
    from byoc_cli.pipeline.recipe import FEATURE_KINDS, preset

    if features is not None and features not in FEATURE_KINDS:
        raise ValueError(f"features must be one of {sorted(FEATURE_KINDS)}, got {features!r}")
    if recipe is None:
        recipe = preset(features)
    elif features is not None and features != recipe.features.kind:
        recipe = recipe.with_kind(features)
    if fallback == "auto":
        fallback = recipe.gate.fallback if recipe.features.kind == "byoc" else "none"
    if fallback not in (None, "none", "fpfh") or (
        fallback == "fpfh" and recipe.features.kind != "byoc"
    ):
        raise ValueError(f"fallback must be None or 'fpfh' (with byoc features), got {fallback!r}")
    path = weights if isinstance(weights, (str, os.PathLike)) else None
    return recipe.changed(
        features__weights=None if path is None else os.fspath(path),
        features__voxel=None if voxel_size is _RECIPE else voxel_size or "own",
        gate__fallback="none" if fallback is None else fallback,
        gate__min_confidence=fallback_below,
    )


class Registrar:
    """A feature extractor loaded once, for many clouds and pairs.

    Args:
        features: ``"byoc"`` (the learned encoder) or ``"fpfh"`` (Open3D FPFH); None: the
            recipe's (without a recipe: the :data:`~byoc_cli.pipeline.recipe.DEFAULT_PRESET`).
        weights: for byoc: a weights file, a :func:`load_weights` result, or None for the
            recipe's (the shipped weights unless the recipe names a file).
        voxel_size: ``"auto"``: read from each pair's clouds, in their own units
            (:mod:`byoc_cli.pipeline.scale`); a number: that voxel, in the units of the
            points; None: the features' own voxel (the weights' voxel size for byoc, the
            preset's for fpfh), with the unit check of :func:`load_cloud`. Not given: the
            recipe's (``"auto"`` in the presets).
        device: ``"cpu"``, ``"cuda"`` or ``"auto"`` (cuda when available).
        threads: worker threads, each running torch single-threaded (default: torch's
            thread count, which the tool's thread policy sets to the usable cores).
        fallback: ``"fpfh"``: when a learned registration's confidence is below
            ``fallback_below``, register the pair again with FPFH features (at the same
            scale, refined the same way) and keep the more confident of the two; None: never;
            ``"auto"``: the recipe's gate (``"fpfh"`` with byoc features, None with fpfh).
        fallback_below: the confidence under which the fallback runs (None: the recipe's
            ``gate.min_confidence``, the default ``--min-confidence``).
        recipe: a :class:`~byoc_cli.pipeline.recipe.RegistrationRecipe` (None: the preset
            of ``features``); the arguments above that are given change it.

    Raises:
        WeightsError: the weights cannot be loaded.
        ValueError: an unknown ``features`` name, ``threads`` below 1.
    """

    def __init__(
        self,
        features: str | None = None,
        weights: str | os.PathLike[str] | LoadedWeights | None = None,
        voxel_size: float | str | None = _RECIPE,
        device: str = "auto",
        threads: int | None = None,
        fallback: str | None = "auto",
        fallback_below: float | None = None,
        *,
        recipe: RegistrationRecipe | None = None,
    ) -> None:
        import torch

        self.recipe = _registrar_recipe(
            recipe, features, weights, voxel_size, fallback, fallback_below
        )
        self.features = self.recipe.features.kind
        gate = self.recipe.gate
        self.fallback = None if gate.fallback == "none" else gate.fallback
        self.fallback_below = float(gate.min_confidence)
        self._fallback_registrar: Registrar | None = None
        if threads is not None and threads < 1:
            raise ValueError(f"threads must be at least 1, got {threads}")
        self.threads = threads or torch.get_num_threads()
        self._executor = None
        self._lock = threading.Lock()
        self.device = _resolve_device(device)
        self.weights_info: dict[str, Any] | None = None
        voxel = self.recipe.features.voxel
        self.auto_voxel = voxel == "auto"
        if weights is None or isinstance(weights, (str, os.PathLike)):
            weights = self.recipe.features.weights
        self.extractor = self._make_extractor(weights, None if voxel in ("auto", "own") else voxel)
        #: the voxel of every cloud when not auto; the reference of the auto choice when auto
        self.voxel_size = float(self.extractor.voxel_size)
        # clouds prepared for multiscale refinement, most recent last: a cloud refined in
        # several pairs (register-batch) builds its levels, normals and search index once
        self._refine_clouds: OrderedDict[int, tuple[np.ndarray, Any]] = OrderedDict()
        # per cloud array, the work a pair's fallback does again: the cloud's measured scale
        # (of the learned registrar) and its features at a voxel (of the fallback's)
        self._scales = _Memo(self.REFINE_CACHE)
        self._features_memo = _Memo(self.REFINE_CACHE)
        # per cloud array, where it is registered (its origin and strays): read by its
        # features and again by its refinement levels
        self._frames = _Memo(self.REFINE_CACHE)

    @property
    def weights_sha256(self) -> str | None:
        return self.weights_info["sha256"] if self.weights_info else None

    #: clouds whose refinement levels are kept
    REFINE_CACHE = 8

    def executor(self):
        """The registrar's worker pool (:func:`byoc_cli.threads.worker_pool`, ``threads``
        workers, one torch thread each), made on first use; submit independent work to it."""
        from byoc_cli.threads import worker_pool

        with self._lock:
            if self._executor is None:
                self._executor = worker_pool(self.threads)
            return self._executor

    def _refine_cloud(self, feats: Features):
        """The :class:`~byoc_cli.pipeline.refine_levels.RefineCloud` of ``feats.cloud`` (kept for
        the ``REFINE_CACHE`` most recently used clouds; its levels are built on use)."""
        from byoc_cli.pipeline.refine_levels import RefineCloud

        key = id(feats.cloud)
        with self._lock:
            hit = self._refine_clouds.get(key)
            voxel = feats.refine_voxel or feats.voxel_size
            if hit is not None and hit[0] is feats.cloud and hit[1].voxel_size == voxel:
                self._refine_clouds.move_to_end(key)
                return hit[1]
            prepared = RefineCloud(self._frame(feats.cloud).local(feats.cloud), voxel)
            self._refine_clouds[key] = (feats.cloud, prepared)  # holds the array: id stays its
            while len(self._refine_clouds) > self.REFINE_CACHE:
                self._refine_clouds.popitem(last=False)
            return prepared

    def prepare_refinement(
        self, feats: Features, source: bool, target: bool, levels: Any = None
    ) -> None:
        """Build the multiscale-refinement ``levels`` (default: all) of ``feats.cloud`` now,
        as a source, a target or both (else :meth:`match` builds them); nothing without a
        cloud. Threads may build different levels of one cloud at once."""
        if feats.cloud is not None:
            self._refine_cloud(feats).prepare(source=source, target=target, levels=levels)

    def _frame(self, points: np.ndarray):
        """:func:`~byoc_cli.geometry.sampling.local_frame` of ``points (N, 3)``, computed once
        per array while among the most recently used."""
        return self._frames.get(points, None, lambda: _local_frame(points))

    def _make_extractor(self, weights: Any, voxel_size: float | None):
        from byoc_cli.pipeline.features import ByocExtractor, FpfhExtractor

        if self.features == "fpfh":
            return FpfhExtractor(voxel_size or self.recipe.features.reference_voxel)
        if weights is None or isinstance(weights, (str, os.PathLike)):
            loaded = load_weights(weights)
        else:
            loaded = weights
        trained_voxel = float(loaded.metadata["voxel_size"])
        if voxel_size is not None and abs(voxel_size - trained_voxel) > 1e-9:
            warnings.warn(
                f"--voxel-size {voxel_size:g} differs from the {trained_voxel:g} m the weights "
                "were trained at",
                stacklevel=3,
            )
        self.weights_info = {
            "path": str(loaded.path),
            "sha256": loaded.file_sha256,
            "architecture": loaded.metadata["architecture"],
            "variant": loaded.metadata["training"]["variant"],
            "code_version": loaded.metadata["code_version"],
        }
        return ByocExtractor(loaded.encoder, voxel_size or trained_voxel, self.device)

    def extract(
        self,
        cloud: Any,
        *,
        scale: float | None = None,
        label: str | None = None,
        intrinsics: str | os.PathLike[str] | None = None,
        depth_scale: float | None = None,
        voxel_size: float | None = None,
    ) -> Features:
        """Features of one cloud (an ``(N, 3)`` array in metres, or a file).

        Args:
            cloud: points or a path (read with :func:`load_cloud`).
            scale: multiply the coordinates by this first (None: check they look like metres,
                unless the voxel is auto).
            label: how errors name the cloud (default: its path, or ``"cloud"``).
            intrinsics, depth_scale: for depth-image files (depth_scale None: the layout's
                around the file, else 1000; :func:`~byoc_cli.api_types.depth_scale_of`).
            voxel_size: this cloud's voxel (a pair's :meth:`choose_voxel`); None: the
                registrar's, or with ``"auto"`` the choice for this cloud alone.

        Raises:
            InputError, ShapeError: unreadable or malformed input.
            RegistrationError: fewer than 3 voxels, a voxel larger than the cloud, collinear,
                (auto) too few points to read a scale from.
        """
        points, name = self.load(
            cloud, label or "cloud", scale, intrinsics=intrinsics, depth_scale=depth_scale
        )
        refine_voxel = None
        if voxel_size is None and self.auto_voxel:
            choice = self.choose_voxel(points, label=label or name)
            voxel_size, refine_voxel = choice.voxel_size, choice.refine_voxel
        return self.extract_points(points, scale, label or name, voxel_size, refine_voxel)

    def load(self, cloud: Any, label: str, scale: float | None, **load: Any):
        """``(points (N, 3) float64, name)`` of an array or a file; the unit check runs only
        when neither ``scale`` nor an auto voxel says what the units are."""
        if scale is None and self.auto_voxel:
            scale = 1.0
        return _as_points(cloud, label, scale, **load)

    def choose_voxel(self, *clouds: np.ndarray, label: str = "cloud", labels=None):
        """The auto voxel of one or two clouds ``(N, 3)`` (a pair shares one):
        a :class:`~byoc_cli.pipeline.scale.VoxelChoice`; ``label`` (one cloud) or ``labels``
        (each cloud) name them in errors.

        Raises:
            RegistrationError: a cloud too small or without extent to read a scale from, or
                two clouds too different in size to be in the same units.
        """
        if labels is None:
            labels = [label] if len(clouds) == 1 else ["source", "target"]
        scales = [self.measure(c, name) for c, name in zip(clouds, labels, strict=True)]
        return self.voxel_for(*scales)

    @staticmethod
    def measure(points: np.ndarray, label: str = "cloud"):
        """How ``points (N, 3)`` are sampled: :class:`~byoc_cli.pipeline.scale.CloudScale`.

        Raises:
            RegistrationError: too few distinct points to read a scale from.
        """
        import torch

        from byoc_cli.pipeline.scale import measure

        return measure(torch.from_numpy(points), label)

    def cloud_scale(self, points: np.ndarray, label: str = "cloud"):
        """:meth:`measure` of ``points (N, 3)``, measured once per array (told by identity:
        arrays the registrar read itself, never changed) while it is among the most recently
        measured (a pair's fallback reads the same clouds' scale, a batch's pairs share
        clouds).

        Raises:
            RegistrationError: too few distinct points to read a scale from.
        """
        scale = self._scales.get(points, None, lambda: self.measure(points, label))
        return scale._replace(label=label)

    def voxel_for(self, *scales: Any):
        r"""The auto voxel of clouds measured with :meth:`measure` (a pair shares one)."""
        from byoc_cli.pipeline.scale import choose_voxel

        return choose_voxel(tuple(scales), self.voxel_size)

    def extract_points(
        self,
        points: np.ndarray,
        scale: float | None,
        label: str,
        voxel_size: float | None = None,
        refine_voxel: float | None = None,
        keep: float = 1.0,
    ) -> Features:
        """Features of ``points (N, 3)`` already in metres, at ``voxel_size`` (None: the
        registrar's); ``refine_voxel``: the refinement's voxel (None: ``voxel_size``);
        ``keep``: the share of the points the features are computed from (a seeded random
        subset; :attr:`~byoc_cli.pipeline.scale.VoxelChoice.keep`). The refinement runs on
        all of them (``Features.cloud``)."""
        import torch

        from byoc_cli.pipeline.scale import check_radius

        voxel = voxel_size or self.voxel_size
        frame = self._frame(points)
        check_radius(frame.radius, label)
        subset = _keep_subset(len(points), keep)
        if frame.inside is not None:  # strays left out
            subset = (
                np.flatnonzero(frame.inside) if subset is None else subset[frame.inside[subset]]
            )
        used = points if subset is None else points[subset]
        used = used - frame.origin if frame.moved else used
        got = self.extractor(torch.from_numpy(used), label=label, voxel_size=voxel)
        index = got.point_index.numpy()
        index = index if subset is None else subset[index]
        return Features(
            points=points[index],
            feats=got.feats.numpy(),
            point_index=index,
            voxel_size=voxel,
            refine_voxel=refine_voxel,
            scale=1.0 if scale is None else float(scale),
            features=self.features,
            weights_sha256=self.weights_sha256,
            cloud=points,
            origin=frame.origin if frame.moved else None,
        )

    def match(
        self,
        src: Features,
        tgt: Features,
        *,
        estimator: str | None = None,
        refine: str | None = None,
        max_points: int | None = None,
        num_correspondences: int | None = None,
        seed: int | None = None,
    ) -> Registration:
        """Register two featured clouds: ratio-test matches, the robust fit, verification.

        The registrar's recipe, changed by the arguments given (None: the recipe's).

        Args:
            src, tgt: :meth:`extract` results (same features, voxel size and scale).
            estimator: ``"ransac"`` or ``"procrustes"``.
            refine: ``"none"`` or ``"multiscale"`` (runs on ``Features.cloud`` where both have
                one).
            max_points: seeded random subset per cloud that enters matching (0 = all).
            num_correspondences: top-k ratio-test matches kept per direction.
            seed: seeds every random choice.

        Raises:
            RegistrationError: no correspondences, or no transform could be fitted.
            ValueError: the two clouds' features do not go together.
        """
        import torch

        from byoc_cli.pipeline.features import CloudFeatures
        from byoc_cli.pipeline.register import estimate_transform, register_config

        src, tgt = self._same_voxel(src, tgt)
        if (src.features, src.voxel_size, src.scale) != (tgt.features, tgt.voxel_size, tgt.scale):
            raise ValueError("src and tgt must have the same features, voxel size and scale")
        recipe = self.recipe_of(estimator, refine, max_points, num_correspondences, seed)
        config = register_config(recipe)
        estimator, refine = recipe.fitting.estimator, recipe.refinement.method
        max_points, num_correspondences = config.max_points, config.num_correspondences
        seed = recipe.seed

        def cloud(f: Features) -> CloudFeatures:
            return CloudFeatures(
                torch.from_numpy(f.points if f.origin is None else f.points - f.origin),
                torch.from_numpy(f.feats),
                torch.from_numpy(f.point_index),
                torch.empty(0, 3, dtype=torch.int64),  # voxel coordinates: unused by matching
            )

        full = None
        if src.cloud is not None and tgt.cloud is not None:
            full = (self._refine_cloud(src), self._refine_cloud(tgt))
        # on a worker (register, register-batch): pieces side by side with an idle worker
        parallel = side_by_side(self.executor()) if in_worker() and self.threads > 1 else None
        result = estimate_transform(
            cloud(src),
            cloud(tgt),
            config,
            src.voxel_size,
            full,
            refine_voxel=src.refine_voxel,
            parallel=parallel,
            scan_lines=self._scan_lines(src, tgt),
        )
        T = _about_origins(result.T_tgt_src.numpy(), src.origin, tgt.origin)
        T[:3, 3] /= src.scale  # back to the input units: a transform of s * x has t / s
        registration = Registration(
            T_tgt_src=T,
            confidence=result.confidence,
            passed=result.confidence >= recipe.gate.min_confidence,
            num_inliers=result.num_inliers,
            num_correspondences=result.num_correspondences,
            inlier_ratio=result.inlier_ratio,
            overlap=result.overlap,
            num_points_src=result.num_points_src,
            num_points_tgt=result.num_points_tgt,
            inlier_threshold=result.inlier_threshold,
            voxel_size=src.voxel_size,
            features=self.features,
            estimator=estimator,
            refine=refine,
            max_points=max_points,
            num_correspondences_per_direction=num_correspondences,
            seed=seed,
            weights_sha256=self.weights_sha256,
            timings=dict(result.timings),
            cues=dict(result.cues),
            recipe=recipe.as_dict(),
        )
        if self.fallback and registration.confidence < self.fallback_below:
            # the recipe of the run (its gate ran the fallback), whichever result is kept
            kept = self._second_opinion(registration, src, tgt, seed)
            passed = kept.confidence >= recipe.gate.min_confidence  # this run's gate
            return kept._replace(recipe=registration.recipe, passed=passed)
        return registration

    def _scan_lines(self, src: Features, tgt: Features) -> bool:
        """Whether a cloud of the pair is sampled along lines
        (:attr:`~byoc_cli.pipeline.scale.CloudScale.line_voxel`, from its :meth:`cloud_scale`)
        with its sensor at the origin: with an auto voxel and both clouds at hand, neither
        registered about another origin (a georeferenced scan's origin is not its sensor's);
        False otherwise."""
        if not self.auto_voxel or src.cloud is None or tgt.cloud is None:
            return False
        if src.origin is not None or tgt.origin is not None:
            return False
        try:
            return any(
                self.cloud_scale(f.cloud, label).line_voxel > 0
                for f, label in ((src, "source"), (tgt, "target"))
            )
        except RegistrationError:  # too few points to read a scale from: no lines to tell
            return False

    def recipe_of(
        self,
        estimator: str | None = None,
        refine: str | None = None,
        max_points: int | None = None,
        num_correspondences: int | None = None,
        seed: int | None = None,
    ) -> RegistrationRecipe:
        """The registrar's recipe changed by :meth:`match`'s arguments (None: unchanged).

        Raises:
            ValueError: a value out of its range (:class:`~byoc_cli.pipeline.recipe.RecipeError`).
        """
        return self.recipe.changed(
            fitting__estimator=estimator,
            refinement__method=refine,
            matching__max_points=max_points,
            matching__correspondences=num_correspondences,
            seed=seed,
        )

    def _second_opinion(
        self, first: Registration, src: Features, tgt: Features, seed: int
    ) -> Registration:
        """``first`` (a learned registration below ``fallback_below``) or, when more
        confident, the fallback features' registration of the same clouds (``src.cloud``,
        ``tgt.cloud``); the result's ``fallback`` says what ran."""
        if src.cloud is None or tgt.cloud is None:
            return first
        start = time.perf_counter()
        with self._lock:
            if self._fallback_registrar is None:
                # FPFH's reference voxel is twice the learned one (5 cm and 2.5 cm)
                voxel = "auto" if self.auto_voxel else 2.0 * self.voxel_size
                self._fallback_registrar = Registrar("fpfh", voxel_size=voxel, threads=1)
        try:
            scales = None
            if self._fallback_registrar.auto_voxel:  # the scales the learned choice read
                scales = [
                    self.cloud_scale(f.cloud, label)
                    for f, label in ((src, "source"), (tgt, "target"))
                ]
            second = self._fallback_registrar._register_clouds(
                (src.cloud, tgt.cloud), scales, refine="multiscale", seed=seed
            )
        except RegistrationError:
            second = None
        seconds = time.perf_counter() - start
        used = second is not None and second.confidence > first.confidence
        note = {
            "features": "fpfh",
            "used": used,
            "learned_confidence": first.confidence,
            "confidence": None if second is None else second.confidence,
            "seconds": seconds,
        }
        timings = {**first.timings, "fallback": seconds}
        if not used:
            return first._replace(timings=timings, fallback=note)
        T = second.T_tgt_src.copy()
        T[:3, 3] /= src.scale
        return second._replace(T_tgt_src=T, timings=timings, fallback=note)

    def _same_voxel(self, src: Features, tgt: Features) -> tuple[Features, Features]:
        """With an auto voxel, two clouds extracted one at a time may have chosen different
        voxels: both are extracted again at the voxel of the pair (from their ``cloud``,
        kept for that). Otherwise ``(src, tgt)`` as they are."""
        same = (src.voxel_size, src.refine_voxel) == (tgt.voxel_size, tgt.refine_voxel)
        if same or not self.auto_voxel or src.cloud is None or tgt.cloud is None:
            return src, tgt
        if src.features != self.features or tgt.features != self.features:
            return src, tgt
        choice = self.choose_voxel(src.cloud, tgt.cloud)
        voxel = (choice.voxel_size, choice.refine_voxel)
        return (
            self.extract_points(src.cloud, src.scale, "source", *voxel, choice.keep_of(0)),
            self.extract_points(tgt.cloud, tgt.scale, "target", *voxel, choice.keep_of(1)),
        )

    def _register_clouds(
        self, clouds: tuple[np.ndarray, np.ndarray], scales: list | None, **settings: Any
    ) -> Registration:
        """What :meth:`register` gives for two arrays already in metres (``scale=1.0``),
        from their :meth:`cloud_scale` ``scales`` (auto voxel; labelled ``"source"`` and
        ``"target"``) and the features of each array
        at its voxel computed once while among the most recent (a fallback registers the
        same clouds in many pairs of a batch); the same result, bytes and all."""
        start = time.perf_counter()
        names = ("source", "target")
        choice, voxels = None, [(None, None, 1.0)] * 2
        if self.auto_voxel:
            for points, scale in zip(clouds, scales, strict=True):  # measured: kept for match
                self._scales.get(points, None, lambda scale=scale: scale)
            choice = self.voxel_for(*scales)
            voxels = [(choice.voxel_size, choice.refine_voxel, choice.keep_of(k)) for k in (0, 1)]
        src, tgt = (
            self._features_memo.get(
                points,
                voxels[k],
                lambda points=points, k=k: self.extract_points(points, 1.0, names[k], *voxels[k]),
            )
            for k, points in enumerate(clouds)
        )
        result = self.match(src, tgt, **settings)
        return result._replace(
            timings={**result.timings, "total": time.perf_counter() - start},
            voxel_choice=None if choice is None else choice.as_dict(),
        )

    def register(
        self,
        source: Any,
        target: Any,
        *,
        scale: float | None = None,
        intrinsics: str | os.PathLike[str] | None = None,
        depth_scale: float | None = None,
        **settings: Any,
    ) -> Registration:
        """Read both clouds, extract their features and :meth:`match` them.

        ``source`` and ``target`` are arrays or files as for :meth:`extract`; ``settings`` are
        :meth:`match`'s keywords. The two clouds are read, encoded and prepared for the
        refinement side by side on the workers. ``timings`` also hold ``load`` (both reads),
        ``features_src``, ``features_tgt``, ``prepare_src``, ``prepare_tgt`` (multiscale
        levels) and ``total`` (wall time).
        """
        start = time.perf_counter()
        load = {"intrinsics": intrinsics, "depth_scale": depth_scale}
        refine = settings.get("refine") or self.recipe.refinement.method
        multiscale = refine == "multiscale"
        pool = _InPlace() if in_worker() else self.executor()
        labels = ((source, "source"), (target, "target"))
        read = [pool.submit(self._loaded, cloud, label, scale, load) for cloud, label in labels]
        (points_src, name_src, size_src, t_src), (points_tgt, name_tgt, size_tgt, t_tgt) = (
            job.result() for job in _all_done(read)
        )
        t_scale = time.perf_counter()
        choice, voxels = None, [(None, None, 1.0)] * 2
        if self.auto_voxel:
            choice = self.voxel_for(size_src, size_tgt)
            voxels = [(choice.voxel_size, choice.refine_voxel, choice.keep_of(k)) for k in (0, 1)]
        t_choice = time.perf_counter() - t_scale
        jobs = [
            pool.submit(
                self._prepared_features,
                points,
                name,
                scale,
                voxels[k],
                multiscale and k == 0,
                multiscale and k == 1,
            )
            for k, (points, name) in enumerate(((points_src, name_src), (points_tgt, name_tgt)))
        ]
        (src, f_src), (tgt, f_tgt) = (job.result() for job in _all_done(jobs))
        result = pool.submit(self.match, src, tgt, **settings).result()
        timings = {
            "load": t_src["load"] + t_tgt["load"],
            "scale": t_src["scale"] + t_tgt["scale"] + t_choice,
            "features_src": f_src["features"],
            "features_tgt": f_tgt["features"],
            "prepare_src": f_src["prepare"],
            "prepare_tgt": f_tgt["prepare"],
            **result.timings,
            "total": time.perf_counter() - start,
        }
        return result._replace(
            timings=timings, voxel_choice=None if choice is None else choice.as_dict()
        )

    def _loaded(
        self, cloud: Any, label: str, scale: float | None, load: dict
    ) -> tuple[np.ndarray, str, Any, dict[str, float]]:
        """Read one cloud and (auto voxel) measure it: ``(points, name, CloudScale | None,
        seconds of each step)``."""
        start = time.perf_counter()
        points, name = self.load(cloud, label, scale, **load)
        loaded = time.perf_counter()
        size = self.cloud_scale(points, name) if self.auto_voxel else None
        return points, name, size, {"load": loaded - start, "scale": time.perf_counter() - loaded}

    def _prepared_features(
        self,
        points: np.ndarray,
        name: str,
        scale: float | None,
        voxel: tuple[float | None, float | None, float],
        as_source: bool,
        as_target: bool,
    ) -> tuple[Features, dict[str, float]]:
        """Extract one cloud's features at ``voxel`` (``(voxel_size, refine_voxel, keep)``)
        and prepare its refinement levels; the features and the seconds of each step."""
        start = time.perf_counter()
        feats = self.extract_points(points, scale, name, *voxel)
        extracted = time.perf_counter()
        if as_target:  # the finer (larger) levels to the next idle worker, the first here
            self.executor().submit(self.prepare_refinement, feats, as_source, True, (2, 1))
            self.prepare_refinement(feats, as_source, True, (0,))
        elif as_source:
            self.prepare_refinement(feats, True, False)
        done = time.perf_counter()
        return feats, {"features": extracted - start, "prepare": done - extracted}


class _Memo:
    """Values of ``(array, key)`` computed once while among the ``size`` most recently used
    (least recently used dropped first); an array is told by its identity (kept alive with
    its value, so that its id is not reused). A thread asking for a value another thread
    computes waits for it; a failure is not kept."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict[tuple[int, Any], tuple[np.ndarray, Future]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, array: np.ndarray, key: Any, compute) -> Any:
        """The value of ``(array, key)``; ``compute()`` makes it on a miss."""
        item = (id(array), key)
        with self._lock:
            hit = self._items.get(item)
            if hit is not None and hit[0] is array:
                self._items.move_to_end(item)
                future = hit[1]
            else:
                future, mine = None, Future()
                self._items[item] = (array, mine)
                self._items.move_to_end(item)
                while len(self._items) > self.size:
                    self._items.popitem(last=False)
        if future is not None:
            return future.result()
        try:
            value = compute()
        except BaseException as exc:
            mine.set_exception(exc)
            with self._lock:
                if self._items.get(item, (None, None))[1] is mine:
                    del self._items[item]
            raise
        mine.set_result(value)
        return value


def _all_done(jobs: list[Future]) -> list[Future]:
    """``jobs``, once every one of them has ended: a cloud that fails to load must not leave
    the other one loading on a worker after :meth:`Registrar.register` has raised (its numpy
    work beside the caller's next call deadlocked OpenBLAS in a test run)."""
    from concurrent.futures import wait

    wait(jobs)
    return jobs


def _local_frame(points: np.ndarray):
    """:func:`~byoc_cli.geometry.sampling.local_frame` of ``points (N, 3)``."""
    from byoc_cli.geometry.sampling import local_frame

    return local_frame(points)


def _about_origins(
    T_local: np.ndarray, origin_src: np.ndarray | None, origin_tgt: np.ndarray | None
) -> np.ndarray:
    """``(4, 4)`` float64 the transform in input coordinates of ``T_local (4, 4)``, which
    maps the source's local points (input minus ``origin_src``) into the target's (input
    minus ``origin_tgt``; None: zeros): ``x_tgt = R (x_src - o_src) + t + o_tgt``."""
    T = np.array(T_local, dtype=np.float64)
    if origin_src is not None:
        T[:3, 3] -= T[:3, :3] @ origin_src
    if origin_tgt is not None:
        T[:3, 3] += origin_tgt
    return T


def _keep_subset(n: int, keep: float) -> np.ndarray | None:
    """A sorted random subset of ``range(n)`` of ``round(keep * n)`` indices (at least 1),
    the same for the same ``n`` and ``keep``; None when ``keep >= 1``."""
    import torch

    if keep >= 1.0 or n == 0:
        return None
    generator = torch.Generator().manual_seed(n)
    count = max(1, round(keep * n))
    return torch.randperm(n, generator=generator)[:count].sort().values.numpy()


class _InPlace:
    """:meth:`submit` runs the call at once (inside a worker, where waiting for the pool
    could wait for oneself)."""

    def submit(self, fn, *args: Any, **kwargs: Any) -> Future:
        future: Future = Future()
        future.set_result(fn(*args, **kwargs))
        return future


def _resolve_device(device: str) -> str:
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda', got {device!r}")
    return device


def extract_features(
    cloud: Any,
    *,
    recipe: RegistrationRecipe | None = None,
    device: str = "auto",
    **overrides: Any,
) -> Features:
    """Per-point features of one cloud (``(N, 3)`` metres or a file); see :class:`Features`.

    ``recipe``, ``device`` and the overrides ``features``, ``weights``, ``voxel_size``: see
    :class:`Registrar`; ``scale``, ``intrinsics``, ``depth_scale``: see
    :meth:`Registrar.extract`. For many clouds build one :class:`Registrar` (the weights are
    loaded once).

    Raises:
        TypeError: an unknown keyword.
    """
    unknown = set(overrides) - {*_REGISTRAR_KEYS, *_LOAD_KEYS} - {"fallback"}
    if unknown:
        raise TypeError(f"extract_features() got unexpected keyword(s) {sorted(unknown)}")
    made = {k: overrides[k] for k in ("features", "weights", "voxel_size") if k in overrides}
    registrar = Registrar(device=device, recipe=recipe, **made)
    return registrar.extract(cloud, **{k: overrides[k] for k in _LOAD_KEYS if k in overrides})


#: :func:`register`'s keywords that go to :class:`Registrar`, to :meth:`Registrar.register`
#: (the clouds' units) and to :meth:`Registrar.match`
_REGISTRAR_KEYS = ("features", "weights", "voxel_size", "fallback")
_LOAD_KEYS = ("scale", "intrinsics", "depth_scale")
_MATCH_KEYS = ("estimator", "refine", "max_points", "num_correspondences", "seed")


def register(
    source: Any,
    target: Any,
    *,
    recipe: RegistrationRecipe | None = None,
    device: str = "auto",
    **overrides: Any,
) -> Registration:
    """Register ``source`` onto ``target`` as ``byoc register`` does (same recipe, same T).

    Args:
        source, target: ``(N, 3)`` arrays in metres, or point-cloud / depth-image files.
        recipe: the :class:`~byoc_cli.pipeline.recipe.RegistrationRecipe` (None: the preset
            of ``features``, the learned features' without it).
        device: see :class:`Registrar`.
        overrides: keywords that change the recipe or say how to read the inputs:
            ``features``, ``weights``, ``voxel_size``, ``fallback`` (see :class:`Registrar`);
            ``estimator``, ``refine``, ``max_points``, ``num_correspondences``, ``seed`` (see
            :meth:`Registrar.match`); ``scale`` (multiply the inputs by this, 0.001 for
            millimetres; T is in the input units), ``intrinsics``, ``depth_scale`` (for
            depth-image files).

    Returns:
        :class:`Registration`.

    Raises:
        InputError, ShapeError, WeightsError, RegistrationError: see :class:`Registrar`.
        TypeError: an unknown keyword.
    """
    unknown = set(overrides) - {*_REGISTRAR_KEYS, *_LOAD_KEYS, *_MATCH_KEYS}
    if unknown:
        raise TypeError(f"register() got unexpected keyword(s) {sorted(unknown)}")
    made = {k: overrides[k] for k in _REGISTRAR_KEYS if k in overrides}
    registrar = Registrar(device=device, recipe=recipe, **made)
    return registrar.register(
        source,
        target,
        **{k: overrides[k] for k in _LOAD_KEYS if k in overrides},
        **{k: overrides[k] for k in _MATCH_KEYS if k in overrides},
    )
