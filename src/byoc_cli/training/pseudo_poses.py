"""Self-posed training pairs: relative poses a sequence gives itself, verified, no ground truth.

For one depth sequence (poses never read):

1. odometry: every consecutive pair of (sub-sampled) frames is registered with coarse-to-fine
   point-to-plane ICP from the identity and from the previous motion (constant velocity); when
   neither fits, a global registration gives the start (FPFH + RANSAC, or in later training
   rounds the learned encoder: ``global_start``). A frame that still does not fit starts a
   new segment (the chain is never bridged by a guess);
2. wide pairs: inside a segment, every ``start_stride``-th frame is paired with the frames
   ``gaps`` later; each pair is registered directly with ICP started from the chained
   odometry (and, when that fails and a ``global_start`` is given, from the global
   registration), and kept as a loop edge when its fit is good (overlap, RMSE) and it agrees
   with the chain within a loose bound (ICP did not slide into another basin);
3. a pose graph of the odometry and loop edges is optimised (Open3D, pruning inconsistent
   edges); a wide pair is kept for training only when its direct estimate agrees with the
   optimised poses, i.e. with every other path between its two frames (cycle consistency).

The kept pairs carry the direct estimate ``T_i_j`` (maps frame ``j`` into frame ``i``).
Accuracy against ground truth is measured by :func:`pair_accuracy`, which the training
never calls.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import numpy as np

from byoc_cli.pipeline import odometry, posegraph

#: the finest ICP correspondence distance as a multiple of the voxel: the pose graph's
FINE_DISTANCE = posegraph.ICP_SCALES[-1][1]
#: frame points farther than this from the camera are dropped (Kinect noise grows with z^2)
DEFAULT_MAX_DEPTH = odometry.DEFAULT_MAX_DEPTH


@dataclass(frozen=True)
class PseudoPoseConfig:
    """Settings of :func:`estimate_pairs` (serialisable with ``dataclasses.asdict``).

    Attributes:
        voxel_size: the fine ICP voxel (metres).
        max_depth: points farther from the camera are dropped (metres).
        frame_stride: use every ``frame_stride``-th frame of the sequence.
        gaps: frame distances (in used frames) of the wide pairs.
        start_stride: a wide pair starts every ``start_stride`` used frames.
        min_fitness: smallest ICP overlap of a kept pair (share of source points matched).
        max_rmse: largest ICP inlier RMSE of a kept pair (metres).
        odometry_min_fitness, odometry_max_rmse: the same for consecutive frames.
        chain_rotation_deg, chain_translation: loose agreement with the chained odometry.
        graph_rotation_deg, graph_translation: tight agreement with the optimised graph.
        seed: seeds RANSAC.
    """

    voxel_size: float = 0.025
    max_depth: float = DEFAULT_MAX_DEPTH
    frame_stride: int = 1
    gaps: tuple[int, ...] = (5, 10, 15, 20, 30, 40, 50, 60)
    start_stride: int = 2
    min_fitness: float = 0.3
    max_rmse: float = 0.025
    odometry_min_fitness: float = 0.6
    odometry_max_rmse: float = 0.025
    chain_rotation_deg: float = 10.0
    chain_translation: float = 0.2
    graph_rotation_deg: float = 2.0
    graph_translation: float = 0.04
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "gaps", tuple(int(g) for g in self.gaps))
        if self.voxel_size <= 0 or self.frame_stride < 1 or self.start_stride < 1:
            raise ValueError("voxel_size must be > 0, frame_stride and start_stride >= 1")
        if not self.gaps or min(self.gaps) < 1:
            raise ValueError(f"gaps must be positive frame distances, got {self.gaps}")


#: ``global_start(src, src_points, tgt, tgt_points) -> T_tgt_src (4, 4) | None``: a global
#: registration of used frame ``src`` onto used frame ``tgt`` (their points ``(N, 3)`` at the
#: fine voxel; the indices let it cache per-frame work); None when it finds no transform
GlobalStart = Callable[[int, np.ndarray, int, np.ndarray], "np.ndarray | None"]


class PseudoPair(NamedTuple):
    """A verified pair: ``T_i_j`` maps the points of frame ``j`` into frame ``i``.

    ``i`` and ``j`` are positions in the sequence's frame list (``i < j``).
    """

    i: int
    j: int
    T_i_j: np.ndarray
    fitness: float
    rmse: float


class SequencePairs(NamedTuple):
    """Result of :func:`estimate_pairs` for one sequence.

    Attributes:
        frames: positions (in the sequence's frame list) of the frames used.
        poses: optimised ``T_seg_frame (4, 4)`` per used frame, relative to its segment start.
        segments: segment id per used frame.
        pairs: the kept wide pairs.
        candidates: per gap, the number of wide pairs tried.
        kept: per gap, the number of wide pairs kept.
        stats: counts of the odometry and of each rejection reason.
    """

    frames: list[int]
    poses: list[np.ndarray]
    segments: list[int]
    pairs: list[PseudoPair]
    candidates: dict[int, int]
    kept: dict[int, int]
    stats: dict[str, int]


# shared with byoc odometry and register-scans (re-exported here for the training code)
frame_points = odometry.frame_points
rotation_angle_deg = posegraph.rotation_angle_deg
transform_difference = posegraph.transform_difference


def _fits(est: Any, min_fitness: float, max_rmse: float) -> bool:
    return est.fitness >= min_fitness and est.rmse <= max_rmse


def _fine_points(cloud: Any) -> np.ndarray:
    """``(N, 3)`` float64 points of a prepared cloud's finest level."""
    return np.asarray(cloud.levels[-1].points)


def _global(clouds, src: int, tgt: int, config: PseudoPoseConfig, global_start):
    """A global start for used frame ``src`` onto ``tgt``: ``(origin, T | None)``."""
    if global_start is None:
        start = posegraph.prepared_fpfh_ransac(clouds[src], clouds[tgt], seed=config.seed + src)
        return "fpfh", start
    T = global_start(src, _fine_points(clouds[src]), tgt, _fine_points(clouds[tgt]))
    return "learned", T


def _odometry_step(
    clouds, k: int, velocity: np.ndarray, config: PseudoPoseConfig, global_start=None
):
    """Register used frame ``k`` onto ``k - 1``; returns the best estimate and its origin."""
    src, tgt = clouds[k], clouds[k - 1]
    tries = [("identity", posegraph.multiscale_icp(src, tgt, np.eye(4)))]
    if not np.allclose(velocity, np.eye(4)):
        tries.append(("velocity", posegraph.multiscale_icp(src, tgt, velocity)))
    best = max(tries, key=lambda t: (t[1].fitness, -t[1].rmse))
    if not _fits(best[1], config.odometry_min_fitness, config.odometry_max_rmse):
        origin, start = _global(clouds, k, k - 1, config, global_start)
        if start is not None:
            tries.append((origin, posegraph.multiscale_icp(src, tgt, start)))
            best = max(tries, key=lambda t: (t[1].fitness, -t[1].rmse))
    return best


def _wide_rejection(est: Any, T_chain: np.ndarray, config: PseudoPoseConfig) -> str | None:
    """Why a direct estimate is not a loop edge (``rejected_fit`` / ``rejected_chain``)."""
    if not _fits(est, config.min_fitness, config.max_rmse):
        return "rejected_fit"
    rot, trans = transform_difference(T_chain, est.T_tgt_src)
    if rot > config.chain_rotation_deg or trans > config.chain_translation:
        return "rejected_chain"
    return None


def _wide_pair(clouds, a: int, b: int, T_chain: np.ndarray, config, global_start):
    """Direct estimate of used frame ``b`` onto ``a``: ``(estimate | None, origin | reason)``.

    ICP starts from the chained odometry (origin ``chain``); when that is rejected and
    ``global_start`` is given, ICP starts again from the global registration, held to the
    same checks (``learned_start``).
    """
    est = _direct(clouds, a, b, T_chain)
    reason = _wide_rejection(est, T_chain, config)
    if reason is None:
        return est, "chain"
    if global_start is not None:
        _, start = _global(clouds, b, a, config, global_start)
        if start is not None:
            again = _direct(clouds, a, b, start)
            if _wide_rejection(again, T_chain, config) is None:
                return again, "learned_start"
    return None, reason


def estimate_pairs(
    sequence: Any,
    config: PseudoPoseConfig | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    global_start: GlobalStart | None = None,
) -> SequencePairs:
    """Estimate, verify and keep wide self-posed pairs of one sequence (see module doc).

    Args:
        sequence: an ``RGBDSequence`` (its poses, if any, are never read).
        config: settings.
        progress: called as ``progress(stage, done, total)``.
        global_start: the global registration of later rounds (e.g. :class:`LearnedStart`);
            None: FPFH + RANSAC where odometry needs a start, the chain alone for wide pairs.

    Returns:
        :class:`SequencePairs`.
    """
    from byoc_cli.pipeline.posegraph import Edge, optimize_pose_graph, prepare_cloud

    config = config or PseudoPoseConfig()
    report = progress or (lambda *_: None)
    frames = list(range(0, len(sequence.frames), config.frame_stride))
    clouds = []
    for n, f in enumerate(frames):
        clouds.append(prepare_cloud(frame_points(sequence, f, config.max_depth), config.voxel_size))
        report("frames", n + 1, len(frames))

    stats = dict.fromkeys(
        ("odometry_identity", "odometry_velocity", "odometry_fpfh", "odometry_learned", "breaks"),
        0,
    )
    segments, chain, odo_edges = [0], [np.eye(4)], []
    velocity = np.eye(4)
    for k in range(1, len(frames)):
        origin, est = _odometry_step(clouds, k, velocity, config, global_start)
        if _fits(est, config.odometry_min_fitness, config.odometry_max_rmse):
            stats[f"odometry_{origin}"] += 1
            segments.append(segments[-1])
            chain.append(chain[-1] @ est.T_tgt_src)
            odo_edges.append(Edge(k, k - 1, est.T_tgt_src, est.information, False))
            velocity = est.T_tgt_src
        else:
            stats["breaks"] += 1
            segments.append(segments[-1] + 1)
            chain.append(np.eye(4))
            velocity = np.eye(4)
        report("odometry", k, len(frames) - 1)

    starts = list(range(0, len(frames), config.start_stride))
    candidates = dict.fromkeys(config.gaps, 0)
    loop_edges, loop_gaps = [], []
    for n, a in enumerate(starts):
        for gap in config.gaps:
            b = a + gap
            if b >= len(frames) or segments[b] != segments[a]:
                continue
            candidates[gap] += 1
            T_chain = np.linalg.inv(chain[a]) @ chain[b]
            est, origin = _wide_pair(clouds, a, b, T_chain, config, global_start)
            if est is None:
                stats[origin] = stats.get(origin, 0) + 1
                continue
            loop_edges.append((Edge(b, a, est.T_tgt_src, est.information, True), est))
            loop_gaps.append((gap, origin))
        report("pairs", n + 1, len(starts))

    poses = list(chain)
    kept_pairs: list[PseudoPair] = []
    kept = dict.fromkeys(config.gaps, 0)
    for seg in sorted(set(segments)):
        nodes = [k for k, s in enumerate(segments) if s == seg]
        if len(nodes) < 2:
            continue
        local = {k: n for n, k in enumerate(nodes)}
        seg_loops = [
            (e, est, g) for (e, est), g in zip(loop_edges, loop_gaps, strict=True) if e.src in local
        ]
        edges = [_local_edge(e, local) for e in odo_edges if e.src in local]
        edges += [_local_edge(e, local) for e, _, _ in seg_loops]
        optimised, edge_kept = optimize_pose_graph(
            [chain[k] for k in nodes], edges, FINE_DISTANCE * config.voxel_size
        )
        for k, pose in zip(nodes, optimised, strict=True):
            poses[k] = pose
        loop_kept = edge_kept[len(edges) - len(seg_loops) :]
        for (edge, est, (gap, origin)), survived in zip(seg_loops, loop_kept, strict=True):
            a, b = edge.tgt, edge.src
            T_graph = np.linalg.inv(poses[a]) @ poses[b]
            rot, trans = transform_difference(T_graph, est.T_tgt_src)
            if not survived:
                stats["rejected_pruned"] = stats.get("rejected_pruned", 0) + 1
            elif rot > config.graph_rotation_deg or trans > config.graph_translation:
                stats["rejected_cycle"] = stats.get("rejected_cycle", 0) + 1
            else:
                kept[gap] += 1
                if origin != "chain":
                    stats[f"kept_{origin}"] = stats.get(f"kept_{origin}", 0) + 1
                kept_pairs.append(
                    PseudoPair(frames[a], frames[b], est.T_tgt_src, est.fitness, est.rmse)
                )
    return SequencePairs(frames, poses, segments, kept_pairs, candidates, kept, stats)


def _direct(clouds, a: int, b: int, T_init: np.ndarray):
    return posegraph.multiscale_icp(clouds[b], clouds[a], T_init)


def _local_edge(edge: Any, local: dict[int, int]) -> Any:
    return edge._replace(src=local[edge.src], tgt=local[edge.tgt])


def pair_accuracy(
    result: SequencePairs, gt_poses: list[np.ndarray | None], config: PseudoPoseConfig
) -> dict[int, dict[str, float]]:
    """Per gap: candidates, kept share, median rotation (deg) / translation (cm) error vs GT.

    Args:
        result: :func:`estimate_pairs` output.
        gt_poses: ground-truth ``T_world_cam`` per frame of the sequence (None: missing).
        config: the settings used (for the gap of each pair).
    """
    by_gap: dict[int, list[tuple[float, float]]] = {g: [] for g in config.gaps}
    position = {f: n for n, f in enumerate(result.frames)}
    for pair in result.pairs:
        gt_i, gt_j = gt_poses[pair.i], gt_poses[pair.j]
        if gt_i is None or gt_j is None:
            continue
        gap = position[pair.j] - position[pair.i]
        by_gap[gap].append(transform_difference(np.linalg.inv(gt_i) @ gt_j, pair.T_i_j))
    table = {}
    for gap in config.gaps:
        errors = np.asarray(by_gap[gap]).reshape(-1, 2)
        tried = result.candidates.get(gap, 0)
        table[gap] = {
            "candidates": tried,
            "kept": result.kept.get(gap, 0),
            "kept_share": result.kept.get(gap, 0) / tried if tried else 0.0,
            "median_rotation_deg": float(np.median(errors[:, 0])) if len(errors) else math.nan,
            "median_translation_cm": float(np.median(errors[:, 1]) * 100)
            if len(errors)
            else math.nan,
            "rotation_acc_2deg": float(np.mean(errors[:, 0] < 2.0)) if len(errors) else math.nan,
            "translation_acc_5cm": float(np.mean(errors[:, 1] < 0.05)) if len(errors) else math.nan,
        }
    return table


def config_dict(config: PseudoPoseConfig) -> dict[str, Any]:
    """JSON-friendly settings."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(config).items()}


def pairs_to_json(result: SequencePairs, config: PseudoPoseConfig, sequence: Any) -> dict:
    """A JSON-friendly record of ``result`` (the cache of a run folder)."""
    return {
        "sequence": str(sequence.root),
        "name": sequence.name,
        "num_frames": len(sequence.frames),
        "config": config_dict(config),
        "frames": result.frames,
        "segments": result.segments,
        "candidates": {str(k): v for k, v in result.candidates.items()},
        "kept": {str(k): v for k, v in result.kept.items()},
        "stats": result.stats,
        "pairs": [
            {
                "i": p.i,
                "j": p.j,
                "T_i_j": np.asarray(p.T_i_j).round(8).tolist(),
                "fitness": round(p.fitness, 6),
                "rmse": round(p.rmse, 6),
            }
            for p in result.pairs
        ],
    }


def pairs_from_json(record: dict) -> list[PseudoPair]:
    """The kept pairs of a :func:`pairs_to_json` record."""
    return [
        PseudoPair(
            int(p["i"]), int(p["j"]), np.asarray(p["T_i_j"], np.float64), p["fitness"], p["rmse"]
        )
        for p in record["pairs"]
    ]


class LearnedStart:
    """A :data:`GlobalStart` from a geometric encoder (the later rounds of self-posing).

    Ratio-test matches of the encoder's features and the robust fit of a recipe (``byoc
    register``'s for learned features by default), without its refinement (ICP follows in
    :func:`estimate_pairs`). Each frame is encoded once.

    Args:
        encoder: a geometric encoder; a frozen copy is used (the argument is not changed).
        voxel_size: the encoder's voxel (metres).
        seed: seeds the subsets and RANSAC (it replaces the recipe's seed).
        recipe: the :class:`~byoc_cli.pipeline.recipe.RegistrationRecipe` of the matching
            and the fit (None: the learned features' preset).
    """

    def __init__(self, encoder: Any, voxel_size: float, seed: int = 0, recipe: Any = None) -> None:
        import copy

        from byoc_cli.pipeline.features import ByocExtractor
        from byoc_cli.pipeline.recipe import preset
        from byoc_cli.pipeline.register import register_config

        self.extract = ByocExtractor(copy.deepcopy(encoder).cpu(), voxel_size)
        recipe = (recipe or preset("byoc")).changed(seed=seed)
        self.config = register_config(recipe, refine=False)
        self.features: dict[int, Any] = {}

    def _features(self, index: int, points: np.ndarray) -> Any:
        import torch

        if index not in self.features:
            self.features[index] = self.extract(torch.from_numpy(points), label=f"frame {index}")
        return self.features[index]

    def __call__(
        self, src: int, src_points: np.ndarray, tgt: int, tgt_points: np.ndarray
    ) -> np.ndarray | None:
        from byoc_cli.errors import RegistrationError
        from byoc_cli.pipeline.register import estimate_transform

        try:
            result = estimate_transform(
                self._features(src, src_points),
                self._features(tgt, tgt_points),
                self.config,
                self.extract.voxel_size,
            )
        except RegistrationError:
            return None
        return result.T_tgt_src.numpy()
