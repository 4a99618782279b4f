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

import hashlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from byoc_cli.errors import DatasetError
from byoc_cli.evaluation.cache import FeatureCache, file_identity
from byoc_cli.evaluation.methods import Method, feature_specs, icp_points
from byoc_cli.evaluation.metrics import (
    correspondence_inlier_ratio,
    error_summary,
    nn_inlier_ratio,
    pose_errors,
    recall_by_group,
    registration_rmse,
)
from byoc_cli.evaluation.progress import NullProgress, Progress
from byoc_cli.io.threedmatch import (
    BenchmarkScene,
    fragment_path,
    read_gt_info,
    read_gt_log,
    read_gt_overlap,
)
from byoc_cli.matching import ratio_test_correspondences
from byoc_cli.pipeline.features import CloudFeatures
from byoc_cli.pipeline.register import sample_subset

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


@dataclass(frozen=True)
class FmrConfig:
    """Settings of :func:`evaluate_fmr` (the protocol's constants by default).

    Attributes:
        tau1: inlier distance (m).
        tau2: inlier-ratio threshold of a recalled pair.
        num_samples: points sampled per fragment (0 = all kept points).
        top_k: ratio-test correspondences kept per direction for ``corr``.
        rmse_threshold: registration recall threshold on the official RMSE (m).
        success_rotation_deg, success_translation_m: the success-rate thresholds.
        seed: base seed of every random choice.
    """

    tau1: float = 0.10
    tau2: float = 0.05
    num_samples: int = 5000
    top_k: int = 200
    rmse_threshold: float = 0.2
    success_rotation_deg: float = 15.0
    success_translation_m: float = 0.30
    seed: int = 0


class BenchmarkPair(NamedTuple):
    """One ground-truth pair.

    Attributes:
        scene: scene name.
        i: target fragment; j: source fragment.
        T_gt: ``(4, 4)`` float64, maps fragment ``j`` into fragment ``i``.
        info: ``(6, 6)`` information matrix, or None when ``gt.info`` lacks the pair.
        overlap: from ``gt_overlap.log``, or None.
        source, target: the fragment files.
    """

    scene: str
    i: int
    j: int
    T_gt: np.ndarray
    info: np.ndarray | None
    overlap: float | None
    source: Path
    target: Path


class PairSet(NamedTuple):
    """Pairs selected for evaluation.

    Attributes:
        pairs: the pairs to evaluate, scene by scene in ``gt.log`` order.
        scenes: the scenes used.
        num_listed: pairs listed by the selected scenes' ``gt.log`` (before ``limit``).
        missing_fragments: fragment files named by ``gt.log`` but absent (``allow_missing``).
        skipped_pairs: ``(scene, i, j)`` left out because a fragment is missing.
    """

    pairs: list[BenchmarkPair]
    scenes: list[BenchmarkScene]
    num_listed: int
    missing_fragments: list[str]
    skipped_pairs: list[tuple[str, int, int]]


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


def pair_seed(seed: int, scene: str, i: int, j: int) -> int:
    """The seed of one pair: a hash of ``(seed, scene, i, j)`` in ``[0, 2**63)``."""
    digest = hashlib.sha256(f"{seed}/{scene}/{i}/{j}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def sample_pair_subsets(
    num_src: int, num_tgt: int, num_samples: int, seed: int
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The subsets of one pair: source first, then target, from one generator seeded ``seed``.

    Same draws as :func:`byoc_cli.pipeline.register.estimate_transform` with
    ``max_points=num_samples`` and the same seed. None means "all points".
    """
    generator = torch.Generator().manual_seed(seed)
    idx_src = sample_subset(num_src, num_samples, generator)
    idx_tgt = sample_subset(num_tgt, num_samples, generator)
    return idx_src, idx_tgt


def load_benchmark_pairs(
    scenes: Sequence[BenchmarkScene], limit: int | None = None, allow_missing: bool = False
) -> PairSet:
    """Read the ground truth of ``scenes`` and check that the fragments exist.

    Args:
        scenes: from :func:`byoc_cli.io.threedmatch.discover_benchmark`.
        limit: at most this many pairs per scene (the first ones of ``gt.log``).
        allow_missing: skip pairs whose fragment is missing instead of raising.

    Returns:
        :class:`PairSet`.

    Raises:
        InputError: a malformed ``gt.log``, ``gt.info`` or ``gt_overlap.log``.
        DatasetError: a fragment named by ``gt.log`` is missing (without ``allow_missing``);
            the message names the fragment and the ``gt.log`` line.
    """
    pairs: list[BenchmarkPair] = []
    missing: list[str] = []
    skipped: list[tuple[str, int, int]] = []
    listed = 0
    for scene in scenes:
        records = read_gt_log(scene.gt_log)
        listed += len(records)
        infos = {}
        if scene.gt_info is not None:
            infos = {(r.i, r.j): r.info for r in read_gt_info(scene.gt_info)}
        overlaps = read_gt_overlap(scene.gt_overlap) if scene.gt_overlap is not None else {}
        if limit is not None:
            records = records[:limit]
        for rec in records:
            source, target = fragment_path(scene, rec.j), fragment_path(scene, rec.i)
            absent = [p for p in (target, source) if not p.is_file()]
            if absent:
                if not allow_missing:
                    raise DatasetError(
                        absent[0],
                        f"fragment not found (named by {scene.gt_log} line {rec.line}, pair "
                        f"{rec.i} {rec.j}); pass --allow-missing to skip such pairs",
                    )
                missing += [str(p) for p in absent if str(p) not in missing]
                skipped.append((scene.name, rec.i, rec.j))
                continue
            pairs.append(
                BenchmarkPair(
                    scene.name,
                    rec.i,
                    rec.j,
                    rec.T_tgt_src,
                    infos.get((rec.i, rec.j)),
                    overlaps.get((rec.i, rec.j)),
                    source,
                    target,
                )
            )
    return PairSet(pairs, list(scenes), listed, missing, skipped)


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


def _feature_metrics(
    src: CloudFeatures, tgt: CloudFeatures, T_gt: torch.Tensor, seed: int, config: FmrConfig
) -> dict[str, Any]:
    idx_src, idx_tgt = sample_pair_subsets(
        len(src.points), len(tgt.points), config.num_samples, seed
    )
    ps, fs = (
        (src.points, src.feats) if idx_src is None else (src.points[idx_src], src.feats[idx_src])
    )
    pt, ft = (
        (tgt.points, tgt.feats) if idx_tgt is None else (tgt.points[idx_tgt], tgt.feats[idx_tgt])
    )
    nn = nn_inlier_ratio(ps, fs, pt, ft, T_gt, config.tau1)
    corr = ratio_test_correspondences(fs, ft, k=config.top_k)
    corr_ratio = correspondence_inlier_ratio(ps[corr.src_idx], pt[corr.tgt_idx], T_gt, config.tau1)
    return {
        "num_points_src": len(src.points),
        "num_points_tgt": len(tgt.points),
        "num_samples_src": int(ps.shape[0]),
        "num_samples_tgt": int(pt.shape[0]),
        "inlier_ratio": nn.inlier_ratio,
        "num_matches": nn.num_matches,
        "recalled": nn.inlier_ratio >= config.tau2,
        "corr_inlier_ratio": corr_ratio,
        "num_correspondences": int(corr.src_idx.numel()),
        "corr_recalled": corr_ratio >= config.tau2,
    }


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
        record["features"][spec.key] = _feature_metrics(src, tgt, T_gt, seed, config)
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
        out = method.register(icp_src, icp_tgt, feats, seed)
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


def _recall_dict(summary) -> dict[str, Any]:
    return {
        "mean_over_scenes": summary.mean,
        "std_over_scenes": summary.std,
        "pooled": summary.pooled,
        "num_pairs": summary.num_pairs,
        "per_scene": {
            scene: {"value": value, "num_pairs": n}
            for scene, (value, n) in summary.per_group.items()
        },
    }


def summarize_fmr(
    records: Sequence[dict[str, Any]], methods: Sequence[Method], config: FmrConfig
) -> dict[str, dict[str, Any]]:
    """Per-method summaries of per-pair records.

    Returns:
        ``{method: {...}}`` with ``fmr``, ``corr_fmr``, ``inlier_ratio``, ``corr_inlier_ratio``
        (each: ``mean_over_scenes``, ``std_over_scenes``, ``pooled``, ``num_pairs``,
        ``per_scene``; None for methods without features), ``registration_recall``
        (official pairs ``j - i > 1`` with ``gt.info``; None when no pair has it),
        ``registration_recall_all_pairs``, ``success_rate``, ``rotation_error_deg`` and
        ``translation_error_cm`` (mean, median over all pairs), ``num_failed``,
        ``seconds_per_pair``.
    """
    scenes = [r["scene"] for r in records]
    out: dict[str, dict[str, Any]] = {}
    for method in methods:
        rows = [r["methods"][method.name] for r in records]
        summary: dict[str, Any] = {"num_pairs": len(records)}
        if method.features is not None and records:
            feats = [r["features"][method.features.key] for r in records]
            summary["fmr"] = _recall_dict(recall_by_group([f["recalled"] for f in feats], scenes))
            summary["corr_fmr"] = _recall_dict(
                recall_by_group([f["corr_recalled"] for f in feats], scenes)
            )
            summary["inlier_ratio"] = _recall_dict(
                recall_by_group(
                    [f["recalled"] for f in feats], scenes, [f["inlier_ratio"] for f in feats]
                )
            )
            summary["corr_inlier_ratio"] = _recall_dict(
                recall_by_group(
                    [f["corr_recalled"] for f in feats],
                    scenes,
                    [f["corr_inlier_ratio"] for f in feats],
                )
            )
        else:
            summary.update(fmr=None, corr_fmr=None, inlier_ratio=None, corr_inlier_ratio=None)
        for key, keep in (
            ("registration_recall", lambda r: r["official"] and r["has_info"]),
            ("registration_recall_all_pairs", lambda r: r["has_info"]),
        ):
            chosen = [r for r in records if keep(r)]
            if chosen:
                flags = [r["methods"][method.name]["registered"] for r in chosen]
                result = _recall_dict(recall_by_group(flags, [r["scene"] for r in chosen]))
                result["num_degenerate_info"] = sum(
                    1
                    for r in chosen
                    if r["methods"][method.name]["rmse_m"] is None
                    or math.isnan(r["methods"][method.name]["rmse_m"])
                )
                summary[key] = result
            else:
                summary[key] = None
        summary["success_rate"] = (
            _recall_dict(recall_by_group([row["success"] for row in rows], scenes))
            if rows
            else None
        )
        rot = error_summary([row["rotation_error_deg"] for row in rows], ())
        trans = error_summary([100.0 * row["translation_error_m"] for row in rows], ())
        summary["rotation_error_deg"] = {"mean": rot.mean, "median": rot.median}
        summary["translation_error_cm"] = {"mean": trans.mean, "median": trans.median}
        summary["num_failed"] = sum(1 for row in rows if row["failed"])
        summary["seconds_per_pair"] = (
            float(np.mean([row["seconds"] for row in rows])) if rows else float("nan")
        )
        out[method.name] = summary
    return out
