"""Feature-match recall and registration on a 3DMatch-layout benchmark (``byoc eval-fmr``).

For every ``gt.log`` pair ``(i, j)`` (source ``j``, target ``i``, ``T_gt`` maps ``j`` into
``i``) and every feature spec:

1. a seeded random subset of ``num_samples`` (5000) kept points of each fragment (the seed is
   :func:`pair_seed`, so a pair's subset does not depend on ``--limit`` or on the order);
2. ``fmr``: FCGF's nearest-neighbour inlier ratio on the subsets (``tau1`` = 0.10 m), the pair
   recalled when it is at least ``tau2`` = 0.05 (:func:`.metrics.nn_inlier_ratio`);
3. ``corr``: the same on the ratio-test correspondences of the subsets (top ``top_k`` = 200 per
   direction, :func:`~byoc_cli.matching.ratio_test_correspondences`).

Then every method registers the pair (feature methods on the same subsets: ``estimate_transform``
draws them from the same seed), and the estimate is scored: rotation and translation errors,
the official RMSE from ``gt.info`` and its recall (RMSE <= 0.2 m over pairs with ``j - i > 1``,
the 3DMatch protocol; also reported over all pairs), and the success rate (rotation error
< 15 deg and translation error < 30 cm, DGR's).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import torch

from byoc_cli.evaluation.benchmark import BenchmarkPair, PairSet, load_benchmark_pairs
from byoc_cli.evaluation.cache import FeatureCache, file_identity
from byoc_cli.evaluation.fmr_protocol import (
    FmrConfig,
    feature_metrics,
    pair_seed,
    sample_pair_subsets,
)
from byoc_cli.evaluation.fmr_summary import summarize_fmr
from byoc_cli.evaluation.methods import Method, feature_specs, icp_points
from byoc_cli.evaluation.metrics import pose_errors, registration_rmse
from byoc_cli.evaluation.progress import NullProgress, Progress
from byoc_cli.pipeline.features import CloudFeatures

__all__ = [
    "BenchmarkPair",
    "FmrConfig",
    "FmrResult",
    "PairSet",
    "evaluate_fmr",
    "load_benchmark_pairs",
    "pair_seed",
    "sample_pair_subsets",
    "summarize_fmr",
]


class FmrResult(NamedTuple):
    """Output of :func:`evaluate_fmr`.

    Attributes:
        records: one JSON-able dict per pair (ground truth, per feature spec and per method).
        summaries: ``{method name: summary dict}`` (see :func:`summarize_fmr`).
        cache_hits, cache_misses: feature cache lookups.
        seconds: wall time of the evaluation.
    """

    records: list[dict[str, Any]]
    summaries: dict[str, dict[str, Any]]
    cache_hits: int
    cache_misses: int
    seconds: float


def _read_fragment(path: Path) -> torch.Tensor:
    from byoc_cli.io.pointcloud import read_point_cloud

    return torch.from_numpy(read_point_cloud(path).points)


class _SceneClouds:
    """Fragments of one scene: raw points (read once), features per spec, ICP clouds."""

    def __init__(self, cache: FeatureCache) -> None:
        self.cache = cache
        self.raw: dict[Path, torch.Tensor] = {}
        self.feats: dict[tuple[str, Path], CloudFeatures] = {}
        self.icp: dict[Path, torch.Tensor] = {}

    def points(self, path: Path) -> torch.Tensor:
        if path not in self.raw:
            self.raw[path] = _read_fragment(path)
        return self.raw[path]

    def features(self, spec, path: Path) -> CloudFeatures:
        key = (spec.key, path)
        if key not in self.feats:
            self.feats[key] = self.cache.get(
                spec.identity,
                file_identity(path),
                lambda: spec.extractor(self.points(path), label=str(path)),
            )
        return self.feats[key]

    def icp_cloud(self, path: Path) -> torch.Tensor:
        if path not in self.icp:
            self.icp[path] = icp_points(self.points(path))
        return self.icp[path]


def evaluate_fmr(
    pair_set: PairSet,
    methods: Sequence[Method],
    config: FmrConfig | None = None,
    cache: FeatureCache | None = None,
    progress: Progress | None = None,
) -> FmrResult:
    """Evaluate every method on every pair of ``pair_set``.

    Args:
        pair_set: from :func:`load_benchmark_pairs`.
        methods: from :func:`byoc_cli.evaluation.methods.build_methods`.
        config: protocol settings.
        cache: feature cache (None: in memory only).
        progress: receives ``features`` (fragments x feature specs) and ``pairs`` steps.

    Returns:
        :class:`FmrResult`.

    Raises:
        InputError: a fragment cannot be read; RegistrationError: a fragment too small to
            voxelise.
    """
    config = config or FmrConfig()
    cache = cache or FeatureCache(None)
    progress = progress or NullProgress()
    specs = feature_specs(methods)
    needs_icp = any(m.kind.startswith("icp") for m in methods)
    started = time.perf_counter()
    by_scene: dict[str, list[BenchmarkPair]] = {}
    for pair in pair_set.pairs:
        by_scene.setdefault(pair.scene, []).append(pair)
    fragments = {
        s: sorted({p.source for p in ps} | {p.target for p in ps}) for s, ps in by_scene.items()
    }
    progress.start("features", sum(len(f) for f in fragments.values()) * len(specs))
    progress.start("pairs", len(pair_set.pairs))
    records: list[dict[str, Any]] = []
    for scene, pairs in by_scene.items():
        clouds = _SceneClouds(cache)
        for spec in specs:
            for path in fragments[scene]:
                clouds.features(spec, path)
                progress.advance("features")
        for pair in pairs:
            records.append(_evaluate_pair(pair, methods, specs, clouds, config, needs_icp))
            progress.advance("pairs")
        clouds.raw.clear()
    summaries = summarize_fmr(records, methods, config)
    return FmrResult(records, summaries, cache.hits, cache.misses, time.perf_counter() - started)


def _evaluate_pair(pair, methods, specs, clouds, config, needs_icp) -> dict[str, Any]:
    T_gt = torch.from_numpy(pair.T_gt)
    seed = pair_seed(config.seed, pair.scene, pair.i, pair.j)
    record: dict[str, Any] = {
        "scene": pair.scene,
        "i": pair.i,
        "j": pair.j,
        "official": pair.j - pair.i > 1,
        "overlap": pair.overlap,
        "has_info": pair.info is not None,
        "features": {},
        "methods": {},
    }
    for spec in specs:
        src = clouds.features(spec, pair.source)
        tgt = clouds.features(spec, pair.target)
        record["features"][spec.key] = feature_metrics(src, tgt, T_gt, seed, config)
    icp_src = clouds.icp_cloud(pair.source) if needs_icp else None
    icp_tgt = clouds.icp_cloud(pair.target) if needs_icp else None
    for method in methods:
        start = time.perf_counter()
        feats = None
        if method.features is not None:
            feats = (
                clouds.features(method.features, pair.source),
                clouds.features(method.features, pair.target),
            )
        full = None
        if method.needs_clouds:
            full = (clouds.points(pair.source), clouds.points(pair.target))
        out = method.register(icp_src, icp_tgt, feats, seed, full)
        seconds = time.perf_counter() - start
        rot, trans = pose_errors(out.T_tgt_src, T_gt)
        rmse = registration_rmse(out.T_tgt_src, T_gt, pair.info) if pair.info is not None else None
        record["methods"][method.name] = {
            "T_est": out.T_tgt_src.tolist(),
            "failed": out.failed,
            "error": out.error,
            "rotation_error_deg": rot,
            "translation_error_m": trans,
            "rmse_m": rmse,
            "registered": bool(rmse is not None and rmse <= config.rmse_threshold),
            "success": bool(
                rot < config.success_rotation_deg and trans < config.success_translation_m
            ),
            "seconds": seconds,
        }
    return record
