"""Pairwise registration accuracy on posed RGB-D video or prepared pairs (``byoc eval-pairs``).

The paper's pairwise table (its section 4.1): rotation error
``arccos((tr(R_est R_gt^T) - 1) / 2)`` in degrees, translation error ``|t_est - t_gt|`` in cm,
and the chamfer distance between the two frames fused with the estimated and with the true
pose (:func:`~byoc_cli.evaluation.metrics.fused_chamfer`, in 1e-3 m^2, on the clouds voxelised
at :data:`CHAMFER_VOXEL_SIZE`); accuracy at 5/10/45 deg, 5/10/25 cm and 1/5/10, mean and
median of each.

Pairs from RGB-D video (:func:`rgbd_pairs`): per sequence with poses, every ``spacing``-th
frame, consecutive ones paired (the paper's test pairs, ``make_pairs(mode="val")``); the later
frame is the source, the earlier the target, ``T_gt = inv(T_world_tgt) @ T_world_src``. The
clouds are the FULL-resolution back-projections of the depth images (pixel centres, OpenCV
axes, missing depth dropped), not the 128x128 training crops; each method voxelises them as
``byoc register`` does.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from byoc_cli.evaluation.cache import FeatureCache, file_identity
from byoc_cli.evaluation.methods import Method, feature_specs, icp_points
from byoc_cli.evaluation.metrics import error_summary, fused_chamfer, pose_errors
from byoc_cli.evaluation.progress import NullProgress, Progress
from byoc_cli.geometry import voxelize

__all__ = [
    "CHAMFER_THRESHOLDS",
    "CHAMFER_VOXEL_SIZE",
    "ROTATION_THRESHOLDS_DEG",
    "TRANSLATION_THRESHOLDS_CM",
    "CloudRef",
    "PairSpec",
    "PairsConfig",
    "PairsResult",
    "evaluate_pairs",
    "prepared_pairs",
    "rgbd_pairs",
    "summarize_pairs",
]

ROTATION_THRESHOLDS_DEG = (5.0, 10.0, 45.0)
TRANSLATION_THRESHOLDS_CM = (5.0, 10.0, 25.0)
#: Chamfer thresholds of the paper's table (values in 1e-3 m^2, see metrics.chamfer_distance).
CHAMFER_THRESHOLDS = (1.0, 5.0, 10.0)
#: Voxel size (m) of the clouds the chamfer distance is computed on.
CHAMFER_VOXEL_SIZE = 0.025
#: Clouds (and their features) kept in memory: consecutive test pairs share a frame.
_MEMORY = 4


@dataclass(frozen=True)
class PairsConfig:
    """Settings of :func:`evaluate_pairs`.

    Attributes:
        seed: base seed of every random choice (one seed per pair, from its name).
        rotation_thresholds_deg, translation_thresholds_cm, chamfer_thresholds: accuracy
            thresholds.
        chamfer_voxel_size: voxel size (m) of the chamfer clouds.
    """

    seed: int = 0
    rotation_thresholds_deg: tuple[float, ...] = ROTATION_THRESHOLDS_DEG
    translation_thresholds_cm: tuple[float, ...] = TRANSLATION_THRESHOLDS_CM
    chamfer_thresholds: tuple[float, ...] = CHAMFER_THRESHOLDS
    chamfer_voxel_size: float = CHAMFER_VOXEL_SIZE


class CloudRef(NamedTuple):
    """A cloud to be read.

    Attributes:
        key: unique within a run (for the in-memory cache).
        identity: JSON-able identity for the feature cache (see ``file_identity``).
        load: returns ``(N, 3)`` float points in metres.
    """

    key: str
    identity: dict[str, Any]
    load: Callable[[], np.ndarray]


class PairSpec(NamedTuple):
    """One pair to register.

    Attributes:
        name: ``<sequence>:<target frame>-<source frame>`` or the prepared pair's folder.
        group: the sequence (or the prepared-pairs folder).
        source, target: the clouds.
        T_gt: ``(4, 4)`` float64 ``T_tgt_src``.
    """

    name: str
    group: str
    source: CloudRef
    target: CloudRef
    T_gt: np.ndarray


class PairsResult(NamedTuple):
    """Output of :func:`evaluate_pairs`.

    Attributes:
        records: one JSON-able dict per pair.
        summaries: ``{method: summary}`` (see :func:`summarize_pairs`).
        motion: summary of the ground-truth motion of the pairs (rotation deg, translation cm).
        cache_hits, cache_misses: feature cache lookups.
        seconds: wall time.
    """

    records: list[dict[str, Any]]
    summaries: dict[str, dict[str, Any]]
    motion: dict[str, Any]
    cache_hits: int
    cache_misses: int
    seconds: float


def rgbd_pairs(
    roots: Sequence[str | Path],
    spacing: int = 20,
    limit: int | None = None,
    depth_scale: float | None = None,
) -> tuple[list[PairSpec], list[dict[str, Any]]]:
    """Test pairs of the posed RGB-D sequences under ``roots``.

    Args:
        roots: folders given to :func:`byoc_cli.io.rgbd.discover_sequences`.
        spacing: frames between the two views.
        limit: at most this many pairs per sequence (the first ones).
        depth_scale: raw depth units per metre (None: the layout's).

    Returns:
        ``(pairs, sequences)``; ``sequences`` describes each sequence used (name, layout,
        frames, skipped frames, pairs, intrinsics source).

    Raises:
        DatasetError: no sequence with poses under a root.
    """
    from byoc_cli.io.rgbd import backproject, discover_sequences, make_pairs

    pairs: list[PairSpec] = []
    described = []
    for root in roots:
        for seq in discover_sequences(root, depth_scale=depth_scale, require_poses=True):
            frame_pairs = make_pairs(len(seq), spacing, mode="val")
            if limit is not None:
                frame_pairs = frame_pairs[:limit]
            name = f"{Path(root).name}/{seq.name}" if seq.name != Path(root).name else seq.name

            def ref(index: int, seq=seq, name=name) -> CloudRef:
                frame = seq.frames[index]
                return CloudRef(
                    key=f"{seq.root}#{index}",
                    identity=file_identity(
                        frame.depth_path,
                        K=seq.K.tolist(),
                        depth_scale=seq.depth_scale,
                        cloud="depth back-projection, full resolution, pixel centres",
                    ),
                    load=lambda: backproject(seq.read_depth(index), seq.K).points,
                )

            for tgt, src in frame_pairs:
                T_gt = np.linalg.inv(seq.pose(tgt)) @ seq.pose(src)
                pairs.append(PairSpec(f"{name}:{tgt}-{src}", name, ref(src), ref(tgt), T_gt))
            described.append(
                {
                    "name": name,
                    "root": str(seq.root),
                    "layout": seq.layout,
                    "frames": len(seq),
                    "skipped_frames": seq.num_skipped,
                    "pairs": len(frame_pairs),
                    "intrinsics": seq.intrinsics_source,
                    "depth_scale": seq.depth_scale,
                }
            )
    return pairs, described


def prepared_pairs(root: str | Path, limit: int | None = None) -> list[PairSpec]:
    """Pairs of a prepared-pairs folder (``NNNN/source.ply, target.ply, T_gt.txt``).

    Raises:
        DatasetError: no pair folder; InputError: a bad ``T_gt.txt``.
    """
    from byoc_cli.io.pointcloud import read_point_cloud
    from byoc_cli.io.threedmatch import discover_prepared_pairs

    found = discover_prepared_pairs(root)
    if limit is not None:
        found = found[:limit]
    group = Path(root).name

    def ref(path: Path) -> CloudRef:
        return CloudRef(str(path), file_identity(path), lambda: read_point_cloud(path).points)

    return [PairSpec(p.name, group, ref(p.source), ref(p.target), p.T_gt) for p in found]


class _Memory:
    """A small least-recently-used store."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.items: OrderedDict = OrderedDict()

    def get(self, key, make):
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key]
        value = make()
        self.items[key] = value
        if len(self.items) > self.size:
            self.items.popitem(last=False)
        return value


def _pair_seed(seed: int, name: str) -> int:
    from byoc_cli.evaluation.fmr_protocol import pair_seed

    return pair_seed(seed, name, 0, 0)


def evaluate_pairs(
    pairs: Sequence[PairSpec],
    methods: Sequence[Method],
    config: PairsConfig | None = None,
    cache: FeatureCache | None = None,
    progress: Progress | None = None,
) -> PairsResult:
    """Register every pair with every method and score the estimates.

    Args:
        pairs: from :func:`rgbd_pairs` or :func:`prepared_pairs`.
        methods: from :func:`byoc_cli.evaluation.methods.build_methods`.
        config: thresholds and seed.
        cache: feature cache (None: in memory only).
        progress: receives ``pairs`` steps.

    Returns:
        :class:`PairsResult`.

    Raises:
        FrameError / InputError: a depth image or cloud cannot be read; RegistrationError:
            a cloud too small to voxelise.
    """
    config = config or PairsConfig()
    cache = cache or FeatureCache(None)
    progress = progress or NullProgress()
    specs = feature_specs(methods)
    needs_icp = any(m.kind.startswith("icp") for m in methods)
    points = _Memory(_MEMORY)
    derived = _Memory(_MEMORY * (len(specs) + 2))
    started = time.perf_counter()
    progress.start("pairs", len(pairs))

    def cloud(ref: CloudRef) -> torch.Tensor:
        return points.get(
            ref.key, lambda: torch.from_numpy(np.asarray(ref.load(), dtype=np.float64))
        )

    def features(spec, ref: CloudRef):
        return derived.get(
            (spec.key, ref.key),
            lambda: cache.get(
                spec.identity, ref.identity, lambda: spec.extractor(cloud(ref), label=ref.key)
            ),
        )

    def voxelised(ref: CloudRef, voxel: float, tag: str) -> torch.Tensor:
        def make() -> torch.Tensor:
            if tag == "icp":
                return icp_points(cloud(ref))
            pts = cloud(ref)
            return pts[voxelize(pts, voxel).point_index]

        return derived.get((tag, ref.key), make)

    records = []
    for pair in pairs:
        T_gt = torch.from_numpy(np.asarray(pair.T_gt, dtype=np.float64))
        seed = _pair_seed(config.seed, pair.name)
        motion_rot, motion_trans = pose_errors(torch.eye(4, dtype=torch.float64), T_gt)
        record: dict[str, Any] = {
            "name": pair.name,
            "group": pair.group,
            "gt_rotation_deg": motion_rot,
            "gt_translation_cm": 100.0 * motion_trans,
            "methods": {},
        }
        chamfer_src = voxelised(pair.source, config.chamfer_voxel_size, "chamfer")
        chamfer_tgt = voxelised(pair.target, config.chamfer_voxel_size, "chamfer")
        icp_src = voxelised(pair.source, 0.0, "icp") if needs_icp else None
        icp_tgt = voxelised(pair.target, 0.0, "icp") if needs_icp else None
        for spec in specs:  # features first, so that method timings exclude them
            features(spec, pair.source)
            features(spec, pair.target)
        for method in methods:
            start = time.perf_counter()
            feats = None
            if method.features is not None:
                feats = (
                    features(method.features, pair.source),
                    features(method.features, pair.target),
                )
            full = (cloud(pair.source), cloud(pair.target)) if method.needs_clouds else None
            out = method.register(icp_src, icp_tgt, feats, seed, full)
            seconds = time.perf_counter() - start
            rot, trans = pose_errors(out.T_tgt_src, T_gt)
            chamfer = fused_chamfer(chamfer_src, chamfer_tgt, out.T_tgt_src, T_gt)
            record["methods"][method.name] = {
                "T_est": out.T_tgt_src.tolist(),
                "failed": out.failed,
                "error": out.error,
                "rotation_error_deg": rot,
                "translation_error_cm": 100.0 * trans,
                "chamfer": chamfer,
                "seconds": seconds,
            }
        records.append(record)
        progress.advance("pairs")
    return PairsResult(
        records,
        summarize_pairs(records, methods, config),
        _motion(records),
        cache.hits,
        cache.misses,
        time.perf_counter() - started,
    )


def _summary_dict(summary) -> dict[str, Any]:
    return {
        "accuracy_percent": {f"{k:g}": v for k, v in summary.accuracy.items()},
        "mean": summary.mean,
        "median": summary.median,
    }


def _motion(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    rot = error_summary([r["gt_rotation_deg"] for r in records], ())
    trans = error_summary([r["gt_translation_cm"] for r in records], ())
    return {
        "rotation_deg": {"mean": rot.mean, "median": rot.median},
        "translation_cm": {"mean": trans.mean, "median": trans.median},
    }


def summarize_pairs(
    records: Sequence[dict[str, Any]], methods: Sequence[Method], config: PairsConfig
) -> dict[str, dict[str, Any]]:
    """Per-method accuracy at the thresholds, mean and median of each error.

    Returns:
        ``{method: {"rotation_deg": {...}, "translation_cm": {...}, "chamfer": {...},
        "num_pairs", "num_failed", "seconds_per_pair"}}``; each error dict has
        ``accuracy_percent`` (threshold -> percent of pairs strictly below), ``mean`` and
        ``median``.
    """
    out = {}
    for method in methods:
        rows = [r["methods"][method.name] for r in records]
        out[method.name] = {
            "num_pairs": len(rows),
            "rotation_deg": _summary_dict(
                error_summary(
                    [r["rotation_error_deg"] for r in rows], config.rotation_thresholds_deg
                )
            ),
            "translation_cm": _summary_dict(
                error_summary(
                    [r["translation_error_cm"] for r in rows], config.translation_thresholds_cm
                )
            ),
            "chamfer": _summary_dict(
                error_summary([r["chamfer"] for r in rows], config.chamfer_thresholds)
            ),
            "num_failed": sum(1 for r in rows if r["failed"]),
            "seconds_per_pair": (
                float(np.mean([r["seconds"] for r in rows])) if rows else float("nan")
            ),
        }
    return out
