"""The register engine: a pair of clouds through its stages, with what it loaded kept for
many pairs.

The stages and where each lives::

    load ──> scale ──> features ──> correspondences, robust fit, refinement, cues ──> fallback
    inputs   scale     featurizer   pair -> register.estimate_transform             fallback

:meth:`Registrar.register` is the sequence of one pair: both clouds are read and measured
side by side on the workers, the pair's voxel is chosen, both clouds' features are extracted
(and the refinement's levels built) side by side, and :meth:`Registrar.match` matches, fits,
refines and judges them; below the gate the FPFH fallback gives a second opinion.

Threads: a :class:`Registrar` runs its work on ``threads`` worker threads (default: torch's
thread count) with one torch thread each (:func:`byoc_cli.threads.worker_pool`);
:meth:`Registrar.executor` lets callers run pairs side by side.
"""

from __future__ import annotations

import os
import threading
from typing import TYPE_CHECKING, Any

from byoc_cli.pipeline.engine_recipe import FROM_RECIPE, registrar_recipe, resolve_device
from byoc_cli.pipeline.fallback import Fallback, large_panoramas
from byoc_cli.pipeline.featurizer import Featurizer
from byoc_cli.pipeline.memo import RefineClouds
from byoc_cli.pipeline.pair import Scans, match_pair, same_voxel, scan_lines
from byoc_cli.pipeline.recheck import checked
from byoc_cli.pipeline.results import Features, Registration
from byoc_cli.pipeline.retries import retried
from byoc_cli.pipeline.sequence import register_either
from byoc_cli.pipeline.turns import with_turns
from byoc_cli.pipeline.visibility import seen
from byoc_cli.threads import in_worker, side_by_side

if TYPE_CHECKING:
    from byoc_cli.pipeline.recipe import RegistrationRecipe
    from byoc_cli.pipeline.weights import LoadedWeights


class Registrar(Featurizer):
    """A feature extractor loaded once, for many clouds and pairs.

    Args:
        features: ``"byoc"`` (the learned encoder) or ``"fpfh"`` (Open3D FPFH); None: the
            recipe's (without a recipe: the :data:`~byoc_cli.pipeline.recipe.DEFAULT_PRESET`).
        weights: for byoc: a weights file, a :func:`~byoc_cli.pipeline.inputs.load_weights`
            result, or None for the recipe's (the shipped weights unless it names a file).
        voxel_size: ``"auto"``: read from each pair's clouds (:mod:`byoc_cli.pipeline.scale`);
            a number: that voxel, in the points' units; None: the features' own voxel, with
            the unit check of :func:`~byoc_cli.pipeline.inputs.load_cloud`. Not given: the
            recipe's (``"auto"`` in the presets).
        device: ``"cpu"``, ``"cuda"`` or ``"auto"`` (cuda when available).
        threads: worker threads, each running torch single-threaded (default: the usable
            cores, torch's thread count under the tool's thread policy).
        fallback: ``"fpfh"``: below ``fallback_below``, register the pair again with FPFH
            (:mod:`byoc_cli.pipeline.fallback`) and keep the more confident result; None:
            never; ``"auto"``: the recipe's gate (``"fpfh"`` with byoc, None with fpfh).
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
        voxel_size: float | str | None = FROM_RECIPE,
        device: str = "auto",
        threads: int | None = None,
        fallback: str | None = "auto",
        fallback_below: float | None = None,
        *,
        recipe: RegistrationRecipe | None = None,
    ) -> None:
        import torch

        recipe = registrar_recipe(recipe, features, weights, voxel_size, fallback, fallback_below)
        if threads is not None and threads < 1:
            raise ValueError(f"threads must be at least 1, got {threads}")
        super().__init__(recipe, weights, resolve_device(device))
        self.fallback = None if recipe.gate.fallback == "none" else recipe.gate.fallback
        self.fallback_below = float(recipe.gate.min_confidence)
        self.turns = recipe.matching.turns if self.features == "byoc" else False
        self.threads = threads or torch.get_num_threads()
        self._executor = None
        self._lock = threading.Lock()
        self._refine = RefineClouds(self.CACHE)
        self._coarse = RefineClouds(self.CACHE)  # the local path's coarse pass
        fallback_voxel = "auto" if self.auto_voxel else 2.0 * self.voxel_size
        self._fallback = Fallback(fallback_voxel, turns=self.turns)

    def executor(self):
        """The registrar's worker pool (:func:`byoc_cli.threads.worker_pool`, ``threads``
        workers, one torch thread each), made on first use; submit independent work to it."""
        from byoc_cli.threads import worker_pool

        with self._lock:
            if self._executor is None:
                self._executor = worker_pool(self.threads)
            return self._executor

    def prepare_refinement(self, feats: Features, source: bool, target: bool, levels=None):
        """Build the refinement ``levels`` (default: all) of ``feats.cloud`` as a source, a
        target or both now, not in :meth:`match` (threads may build different levels at once)."""
        if feats.cloud is not None:
            self.refinement_cloud(feats).prepare(source=source, target=target, levels=levels)

    def refinement_cloud(self, points, voxel: float | None = None, within: Any = None):
        """The ``RefineCloud`` of ``points (N, 3)`` (local frame) at ``voxel``, kept for later
        pairs; ``points`` a :class:`Features`: its cloud at its refinement voxel; ``within``:
        the one whose finest averages make it (the local path's coarse pass)."""
        if isinstance(points, Features):
            points, voxel = points.cloud, points.refine_voxel or points.voxel_size
        if within is not None:
            return self._coarse.get(points, voxel, lambda: within.average(0), pyramid=True)
        return self._refine.get(points, voxel, lambda: self.frame(points).local(points))

    def recipe_of(
        self,
        estimator: str | None = None,
        refine: str | None = None,
        max_points: int | None = None,
        num_correspondences: int | None = None,
        seed: int | None = None,
    ) -> RegistrationRecipe:
        """The registrar's recipe changed by :meth:`match`'s arguments (None: unchanged);
        ``ValueError`` (:class:`~byoc_cli.pipeline.recipe.RecipeError`) for a value out of range.
        """
        return self.recipe.changed(
            fitting__estimator=estimator,
            refinement__method=refine,
            matching__max_points=max_points,
            matching__correspondences=num_correspondences,
            seed=seed,
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
        turned: Any = None,
    ) -> Registration:
        """Register two featured clouds: :func:`~byoc_cli.pipeline.pair.match_pair`, then the
        retries, :mod:`~byoc_cli.pipeline.recheck`, :mod:`~byoc_cli.pipeline.turns`, fallback,
        :mod:`~byoc_cli.pipeline.visibility`.

        Args:
            src, tgt: :meth:`extract` results (same features, voxel size and scale; with an
                auto voxel, clouds extracted one at a time are extracted again at the pair's).
            estimator: ``"ransac"``, ``"procrustes"`` or ``"sc2"``; None (all): the recipe's.
            refine: ``"none"`` or ``"multiscale"`` (on ``Features.cloud`` where both have one).
            max_points: seeded random subset per cloud that enters matching (0 = all).
            num_correspondences: top-k ratio-test matches kept per direction.
            seed: seeds every random choice.
            turned: the source's features turned (:func:`~byoc_cli.pipeline.turns.source_turner`).

        Raises:
            RegistrationError: no correspondences, or no transform could be fitted.
            ValueError: the two clouds' features do not go together.
        """
        settings = {"estimator": estimator, "refine": refine, "max_points": max_points}
        settings.update(num_correspondences=num_correspondences, seed=seed)
        recipe = self.recipe_of(estimator, refine, max_points, num_correspondences, seed)
        registration = self.match_alone(src, tgt, **settings)
        registration = retried(self, registration, (src, tgt), settings, recipe)
        registration = checked(self, registration, (src, tgt), settings, recipe)
        first = registration.confidence  # the fallback answers to the first learned result
        registration, done = with_turns(self, registration, (src, tgt), turned, settings)
        if not done and self.fallback and first < self.fallback_below:
            kept = self._fallback.second_opinion(self, registration, src, tgt, recipe.seed)
            passed = kept.confidence >= recipe.gate.min_confidence  # this run's gate
            registration = kept._replace(recipe=registration.recipe, passed=passed)
        return seen(self, registration, (src, tgt), recipe)

    def match_alone(self, src: Features, tgt: Features, **settings: Any) -> Registration:
        """:meth:`match` (``settings``: its keywords) without the fallback, whatever the confidence
        (a smooth pair's second opinion is the learned features': :mod:`.feature_choice`)."""
        src, tgt = same_voxel(self, src, tgt)
        if (src.features, src.voxel_size, src.scale) != (tgt.features, tgt.voxel_size, tgt.scale):
            raise ValueError("src and tgt must have the same features, voxel size and scale")
        rooms = large_panoramas(self, src, tgt)  # laser scans of rooms: their turns checked
        recipe = self.recipe_of(**settings)
        full = None
        if src.cloud is not None and tgt.cloud is not None:
            full = (self.refinement_cloud(src), self.refinement_cloud(tgt))
        # on a worker (register, register-batch): pieces side by side with an idle worker
        parallel = side_by_side(self.executor()) if in_worker() and self.threads > 1 else None
        return match_pair(
            src,
            tgt,
            recipe,
            full,
            features=self.features,
            weights_sha256=self.weights_sha256,
            parallel=parallel,
            scans=Scans(scan_lines(self, src, tgt), rooms),
        )

    def fpfh_registration(self, clouds: tuple, scales: list, seed=None, changes=(), coarser=1.0):
        """:meth:`Fallback.register <byoc_cli.pipeline.fallback.Fallback.register>` of
        ``clouds`` (seed None: the recipe's): FPFH's registration, T in metres."""
        seed = self.recipe.seed if seed is None else seed
        return self._fallback.register(clouds, scales, seed, changes, coarser)

    def register(
        self,
        source: Any,
        target: Any,
        *,
        scale: float | None = None,
        intrinsics: str | os.PathLike[str] | None = None,
        depth_scale: float | None = None,
        init: Any = None,
        **settings: Any,
    ) -> Registration:
        """Read both clouds, extract their features and :meth:`match` them
        (:func:`~byoc_cli.pipeline.sequence.register_pair`); from ``init``, a ``(4, 4)`` guess
        of ``T_tgt_src`` (input units), the local registration
        (:func:`~byoc_cli.pipeline.sequence.register_either`).

        ``source`` and ``target`` are arrays or files as for :meth:`extract`, ``scale``,
        ``intrinsics`` and ``depth_scale`` say how to read them; ``settings`` are
        :meth:`match`'s keywords, ``max_correction`` and ``init_mode``. ``timings`` also hold
        ``load``, ``scale``, ``features_src``, ``features_tgt``, ``prepare_src``,
        ``prepare_tgt`` (multiscale levels) and ``total`` (wall time)."""
        load = {"intrinsics": intrinsics, "depth_scale": depth_scale}
        return register_either(self, (source, target), scale, load, settings, init)
