"""The pairs of ``register-batch`` run side by side: one registrar, one cache of clouds and
features shared by its worker threads, each pair's T file written in list order.

:class:`PairRunner` never raises for a bad pair: its summary record
(:func:`byoc_cli.cli.batch_summary.pair_record`) says why, and the other pairs go on.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

from byoc_cli.cli.batch_summary import FAILED, LOW_CONFIDENCE, OK, pair_record
from byoc_cli.cli.pairwise import registration_report

log = logging.getLogger("byoc")


class FeatureCache:
    """The features of the last ``size`` clouds used (least recently used goes first).

    Shared by the worker threads: a cloud asked for while another thread computes it is
    waited for, not computed twice; a failed computation is not kept (each pair that asks
    again gets the error again).
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict[Any, Future] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Any, compute) -> tuple[Any, bool]:
        """``(features, was_cached)``; ``compute()`` makes them on a miss."""
        with self._lock:
            future = self._items.get(key)
            if future is not None:
                self._items.move_to_end(key)
            else:
                self._items[key] = mine = Future()
                if len(self._items) > self.size:
                    self._items.popitem(last=False)
        if future is not None:
            return future.result(), True
        try:
            value = compute()
        except BaseException as exc:
            mine.set_exception(exc)
            with self._lock:
                if self._items.get(key) is mine:
                    del self._items[key]
            raise
        mine.set_result(value)
        return value, False


class PairRunner:
    """Registers pairs with the shared registrar and feature cache, on the registrar's worker
    threads (:meth:`in_order`), and writes each pair's T file (:meth:`finish`, in the
    calling thread, in list order); never raises for a bad pair (its record says why)."""

    #: pairs submitted ahead of the one being written, per worker thread
    AHEAD = 2

    def __init__(self, registrar, cache, load: dict, gate: dict, inputs) -> None:
        self.registrar, self.cache, self.load, self.inputs = registrar, cache, load, inputs
        self.min_confidence, self.device = gate["min_confidence"], gate["device"]
        #: ``max_correction`` and ``init_mode`` of the pairs with an init column
        self.init = {k: gate.get(k) for k in ("max_correction", "init_mode")}

    def in_order(self, todo) -> Iterator[tuple[Any, float]]:
        """:meth:`compute` of every ``(entry, output)`` of ``todo``, run side by side on the
        registrar's workers (at most ``AHEAD`` per worker in flight, so a killed run loses
        only those), yielded in list order."""
        pool = self.registrar.executor()
        window = self.AHEAD * self.registrar.threads
        pending: deque[Future] = deque()
        try:
            for entry, _ in todo:
                pending.append(pool.submit(self.compute, entry))
                if len(pending) >= window:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:  # interrupted: the pairs not started yet are dropped
            for future in pending:
                future.cancel()

    def compute(self, entry) -> tuple[Any, float]:
        """``(registration or the exception, seconds)`` of one pair (a smooth pair starts with
        FPFH: :mod:`byoc_cli.pipeline.feature_choice`)."""
        from byoc_cli.pipeline.feature_choice import (
            LEARNED_SECOND_OPINION,
            applies,
            features_for,
            smooth_first,
        )
        from byoc_cli.pipeline.turns import source_turner

        started = time.perf_counter()
        timings: dict[str, float] = {}
        try:
            (factor_src, factor_tgt), _ = self.load["factors"]
            cloud_src = self._cloud(entry.source, "source", factor_src, timings)
            cloud_tgt = self._cloud(entry.target, "target", factor_tgt, timings)
            guess = self._guess(entry)
            local = guess is not None and guess.mode == "local"
            choice, voxels = None, [(None, None, 1.0)] * 2
            if self.registrar.auto_voxel:  # the features' voxel needs the scan lines
                scales = [self._scale(cloud, not local) for cloud in (cloud_src, cloud_tgt)]
                choice = self.registrar.voxel_for(*scales)
                voxels = [
                    (choice.voxel_size, choice.refine_voxel, choice.keep_of(k)) for k in (0, 1)
                ]
            if local:
                return self._local(cloud_src, cloud_tgt, choice, guess, timings), _since(started)
            picked = None
            if choice is not None and applies(self.registrar):
                clouds = (cloud_src[0], cloud_tgt[0])
                picked = features_for(self.registrar, clouds, choice.voxel_size, scales)

            def learned(second_opinion: bool = True):
                src = self._features(cloud_src, voxels[0], timings, "features_src")
                tgt = self._features(cloud_tgt, voxels[1], timings, "features_tgt")
                if not second_opinion:
                    return self.registrar.match_alone(src, tgt)
                units = self.load["factors"][0][1]
                turned = source_turner(self.registrar, src, units, cloud_src[1], voxels[0])
                return self.registrar.match(src, tgt, turned=turned)

            if picked is not None and picked.first == "fpfh":
                second = (lambda: learned(False)) if LEARNED_SECOND_OPINION else None
                result = smooth_first(self.registrar, clouds, scales, second, picked, factor_tgt)
                if result.voxel_choice is None:  # the learned features' result
                    result = result._replace(voxel_choice=choice.as_dict())
                result = result._replace(timings={**timings, **result.timings})
            else:
                result = learned()
                result = result._replace(
                    timings={**timings, **result.timings},
                    voxel_choice=None if choice is None else choice.as_dict(),
                    features_choice=None if picked is None else picked.as_dict(),
                )
            if guess is not None:
                from byoc_cli.pipeline.local import check_global

                pair = self._pair(cloud_src, cloud_tgt, choice)
                result = check_global(self.registrar, result, pair, guess, dict(timings))
        except Exception as exc:  # one bad pair must not stop the others
            result = exc
        return result, time.perf_counter() - started

    def _guess(self, entry):
        """The :class:`~byoc_cli.pipeline.local.InitialPose` of the pair's init column (None:
        the line has none).

        Raises:
            InputError: the init file cannot be read as a rigid 4x4 transform.
        """
        if entry.init is None:
            return None
        from byoc_cli.io import read_transform
        from byoc_cli.pipeline.local import InitialPose

        T_init = read_transform(entry.init)
        return InitialPose.of(
            T_init, self.init["max_correction"], self.init["init_mode"] or "local"
        )

    def _pair(self, cloud_src, cloud_tgt, choice):
        """The :class:`~byoc_cli.pipeline.local.LocalPair` of two cached clouds and the pair's
        voxel choice (None: the registrar's voxel); ``T`` in the target's units."""
        from byoc_cli.pipeline.local import LocalPair

        units = self.load["factors"][0][1]
        voxel = self.registrar.voxel_size if choice is None else choice.refine_voxel
        as_dict = None if choice is None else choice.as_dict()
        return LocalPair((cloud_src[0], cloud_tgt[0]), voxel, units or 1.0, as_dict)

    def _local(self, cloud_src, cloud_tgt, choice, guess, timings: dict):
        """The local registration of a pair from its initial pose (no features)."""
        from byoc_cli.pipeline.local import register_local

        pair = self._pair(cloud_src, cloud_tgt, choice)
        return register_local(self.registrar, pair, guess.T, guess.trust, timings)

    def _cloud(self, path: Path, label: str, factor: float | None, timings: dict):
        """``(points, name, CloudScale | None, key)`` of a file times its ``factor`` to metres,
        read (and measured for an auto voxel) once while it stays in the cache."""
        start = time.perf_counter()
        key = ("cloud", path.resolve(), factor)

        def read():
            load = {k: self.load[k] for k in ("intrinsics", "depth_scale")}
            points, name = self.registrar.load(path, label, factor, **load)
            auto = self.registrar.auto_voxel
            size = self.registrar.cloud_scale(points, name, lines=False) if auto else None
            return points, name, size, key

        cloud, cached = self.cache.get(key, read)
        timings["load"] = timings.get("load", 0.0) + (
            0.0 if cached else time.perf_counter() - start
        )
        return cloud

    def _scale(self, cloud, lines: bool):
        """The cached ``cloud``'s :class:`~byoc_cli.pipeline.scale.CloudScale`, with its scan
        lines when ``lines`` (measured on first use)."""
        points, name, size, _ = cloud
        return self.registrar.cloud_scale(points, name) if lines else size

    def _features(self, cloud, voxel: tuple, timings: dict, stage: str):
        """Features at ``voxel``, ``(voxel_size, refine_voxel, keep)`` (None, None, 1.0:
        the registrar's); their ``scale`` is the target's factor (T in the target's units)."""
        start = time.perf_counter()
        points, name, _, key = cloud
        units = self.load["factors"][0][1]
        feats, cached = self.cache.get(
            ("features", key, voxel),
            lambda: self.registrar.extract_points(points, units, name, *voxel),
        )
        timings[stage] = 0.0 if cached else time.perf_counter() - start
        return feats

    def finish(self, entry, output: Path, computed: tuple[Any, float]) -> dict:
        """Write the T file of a :meth:`compute` result; the pair's summary record."""
        from byoc_cli.io import atomic_write_text, format_transform
        from byoc_cli.io.outputs import OutputSet

        result, seconds = computed
        try:
            if isinstance(result, Exception):
                raise result
            policy = OutputSet(self.inputs)
            policy.claim(output)
            with policy:  # the T file appears complete, or not at all
                atomic_write_text(output, format_transform(result.T_tgt_src))
        except Exception as exc:  # one bad pair must not stop the others
            log.debug("pair on line %d failed", entry.line, exc_info=True)
            message = " ".join(str(exc).split()) or type(exc).__name__
            return pair_record(entry, output, FAILED, message)
        factors, factors_given = self.load["factors"]
        run = {
            "min_confidence": self.min_confidence,
            "scale": self.load["scale"],
            "factors": factors,
            "factors_given": factors_given,
            "depth_scale": self.load["depth_scale"],
            "device": self.device,
            "started": time.perf_counter(),
            "init_file": entry.init,
        }
        report = registration_report(result, self.registrar, (entry.source, entry.target), run)
        del report["timings_s"]["command"]
        report["timings_s"]["pair"] = seconds
        return {**pair_record(entry, output, OK if result.passed else LOW_CONFIDENCE), **report}


def _since(start: float) -> float:
    return time.perf_counter() - start
