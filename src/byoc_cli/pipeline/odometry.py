"""Depth odometry: the camera trajectory of an RGB-D video by frame-to-keyframe ICP.

For each frame (sub-sampled by ``frame_stride``), back-projected and prepared for the
refinement (:func:`byoc_cli.pipeline.refine_pairs.pair_cloud`):

1. coarse-to-fine point-to-plane ICP (:func:`byoc_cli.pipeline.refine_pairs.refine_pair`, the
   refinement of ``byoc register``, at the finest voxel ``voxel_size``) onto the current
   KEYFRAME, started from the GIVEN motion when there is one (``motions``: the previous
   frame's pose times a given trajectory's motion, :mod:`byoc_cli.pipeline.motion_prior`),
   else (or when that does not fit) from the constant
   velocity prediction (the last frame-to-frame motion applied once more); if that does not
   fit (fitness, RMSE), from the previous frame's pose; if neither fits, from a GLOBAL start
   (``global_start``: FPFH + RANSAC by default, the learned features in ``byoc odometry
   --features byoc``);
2. the frame becomes the new keyframe when its motion from the keyframe exceeds
   ``keyframe_rotation_deg`` or ``keyframe_translation``, or its fitness drops below
   ``keyframe_min_fitness``;
3. a frame that no start fits is LOST: it keeps the given motion's (else the constant-velocity)
   prediction, is reported,
   and starts a new keyframe (and a new segment of the pose graph) unless it has (almost) no
   depth, then the keyframe stays;
4. optionally (``pose_graph``), a pose graph over the keyframes of each segment: the
   keyframe-to-keyframe tracking edges plus loop edges between keyframes close in space,
   registered directly by ICP; optimised with Open3D (pruning wrong loops); every frame then
   follows its keyframe.

Poses are camera-to-world ``T_world_cam (4, 4)`` float64 with the first used frame as the
world; the ground truth of the sequence is never read.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import numpy as np

from byoc_cli.errors import RegistrationError
from byoc_cli.pipeline import posegraph, refine_pairs
from byoc_cli.pipeline.motion_prior import relative_motions
from byoc_cli.pipeline.refine_levels import RefineCloud
from byoc_cli.pipeline.refine_pairs import PairFit

#: frame points farther than this from the camera are dropped (Kinect noise grows with z^2)
DEFAULT_MAX_DEPTH = 4.0

#: ``global_start(points_src (N, 3), points_tgt (M, 3)) -> T_tgt_src (4, 4)``
GlobalStart = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class OdometryConfig:
    """Settings of :func:`estimate_trajectory` (serialisable with :func:`dataclasses.asdict`).

    Attributes:
        voxel_size: the finest ICP voxel, metres (the refinement's levels run at 2.5, 1.25
            and 1 times it).
        max_depth: points farther from the camera are dropped, metres.
        frame_stride: use every ``frame_stride``-th frame.
        max_frames: use at most this many frames (0: all).
        min_fitness, max_rmse: an ICP result is accepted with at least this fitness (share
            of the frame's points matched) and at most this inlier RMSE (metres).
        keyframe_rotation_deg, keyframe_translation, keyframe_min_fitness: a new keyframe
            past this rotation (degrees) or translation (metres) from the keyframe, or below
            this fitness.
        pose_graph: optimise a pose graph over the keyframes (loop edges, pruning).
        loop_max_distance: keyframes whose centres are closer than this (metres) are tried
            as a loop edge ...
        loop_max_rotation_deg: ... when their viewing directions differ by less than this.
        loop_max_candidates: per keyframe, at most this many (nearest) earlier keyframes.
        loop_min_fitness: smallest ICP fitness of a kept loop edge.
        seed: seeds the global start.
    """

    voxel_size: float = 0.025
    max_depth: float = DEFAULT_MAX_DEPTH
    frame_stride: int = 1
    max_frames: int = 0
    min_fitness: float = 0.6
    max_rmse: float = 0.025
    keyframe_rotation_deg: float = 10.0
    keyframe_translation: float = 0.1
    keyframe_min_fitness: float = 0.8
    pose_graph: bool = False
    loop_max_distance: float = 0.5
    loop_max_rotation_deg: float = 30.0
    loop_max_candidates: int = 5
    loop_min_fitness: float = 0.3
    seed: int = 0

    def __post_init__(self) -> None:
        if self.voxel_size <= 0 or self.max_depth <= 0:
            raise ValueError("voxel_size and max_depth must be > 0")
        if self.frame_stride < 1 or self.max_frames < 0 or self.loop_max_candidates < 0:
            raise ValueError("frame_stride must be >= 1, max_frames and loop candidates >= 0")


class Trajectory(NamedTuple):
    """Result of :func:`estimate_trajectory`.

    Attributes:
        frames: positions (in the sequence's frame list) of the frames used.
        poses: ``(F, 4, 4)`` float64 ``T_world_cam`` per used frame (world = the first).
        keyframes: positions in ``frames`` of the keyframes.
        lost: positions in ``frames`` of the frames no start fitted (pose predicted).
        fitness: ``(F,)`` ICP fitness of each frame against its keyframe (1 for the first
            frame, NaN for lost ones).
        stats: counts: which start fitted each frame, keyframes, loops tried/kept/pruned.
        timings: seconds per stage.
    """

    frames: list[int]
    poses: np.ndarray
    keyframes: list[int]
    lost: list[int]
    fitness: np.ndarray
    stats: dict[str, int]
    timings: dict[str, float]


def frame_points(sequence: Any, index: int, max_depth: float = DEFAULT_MAX_DEPTH) -> np.ndarray:
    """Back-project frame ``index`` of ``sequence`` at full resolution: ``(N, 3)`` float32.

    Reads only the depth image and the intrinsics (never a pose).
    """
    from byoc_cli.io.rgbd import backproject

    depth = sequence.read_depth(index)
    depth = np.where(depth <= max_depth, depth, 0.0).astype(np.float32)
    return np.asarray(backproject(depth, sequence.K).points, dtype=np.float32)


def used_frames(num_frames: int, config: OdometryConfig) -> list[int]:
    """Positions of the frames :func:`estimate_trajectory` uses (stride, then the cap)."""
    frames = list(range(0, num_frames, config.frame_stride))
    return frames[: config.max_frames] if config.max_frames else frames


def _fits(est: PairFit, config: OdometryConfig) -> bool:
    return est.fitness >= config.min_fitness and est.rmse <= config.max_rmse


def _global_start_of(global_start: GlobalStart | None, config: OdometryConfig) -> Callable:
    """The global start on prepared clouds: ``global_start`` on their finest level's points,
    or FPFH + RANSAC (:func:`byoc_cli.pipeline.posegraph.fpfh_ransac`)."""

    def start(src: RefineCloud, tgt: RefineCloud) -> np.ndarray:
        if global_start is None:
            return posegraph.fpfh_ransac(
                src.points.numpy(), tgt.points.numpy(), config.voxel_size, seed=config.seed
            )
        return global_start(fine_points(src), fine_points(tgt))

    return start


def fine_points(cloud: RefineCloud) -> np.ndarray:
    """``(N, 3)`` float64 points of a prepared cloud's finest level (voxel averages)."""
    return cloud.average(len(cloud.levels) - 1).numpy()


def _track(
    cloud: RefineCloud,
    key: RefineCloud,
    T_key_prev: np.ndarray,
    velocity: np.ndarray,
    global_start: Callable,
    config: OdometryConfig,
    given: np.ndarray | None = None,
) -> tuple[str, PairFit]:
    """Register a frame onto its keyframe (``given``: the given motion from the previous
    frame, tried first); returns the start that fitted (or the best try)."""
    tries = []
    starts = [("velocity", T_key_prev @ velocity), ("previous", T_key_prev)]
    if given is not None:
        starts.insert(0, ("init", T_key_prev @ given))
    for origin, start in starts:
        est = refine_pairs.refine_pair(cloud, key, start)
        if _fits(est, config):
            return origin, est
        tries.append((origin, est))
    est = refine_pairs.refine_pair(cloud, key, global_start(cloud, key))
    tries.append(("global", est))
    return max(tries, key=lambda t: (_fits(t[1], config), t[1].fitness, -t[1].rmse))


def _is_keyframe(T_key_cur: np.ndarray, fitness: float, config: OdometryConfig) -> bool:
    rotation = posegraph.rotation_angle_deg(T_key_cur[:3, :3])
    translation = float(np.linalg.norm(T_key_cur[:3, 3]))
    return (
        rotation > config.keyframe_rotation_deg
        or translation > config.keyframe_translation
        or fitness < config.keyframe_min_fitness
    )


class _Tracked(NamedTuple):
    """The tracking pass: per frame its keyframe and the pose relative to it."""

    poses: list[np.ndarray]
    reference: list[int]  # per frame: the keyframe it is expressed in
    T_ref_frame: list[np.ndarray]
    keyframes: list[int]
    segments: list[int]  # per keyframe
    edges: list[posegraph.Edge]  # keyframe -> previous keyframe, node ids = keyframe order
    lost: list[int]
    fitness: list[float]


class _Starts(NamedTuple):
    """Where tracking starts besides the frames themselves: the global start on prepared
    clouds, and per frame the given motion from the previous frame (or None)."""

    global_start: Callable
    motions: list[np.ndarray | None]


def _tracking_pass(
    load: Callable[[int], RefineCloud],
    num: int,
    starts: _Starts,
    config: OdometryConfig,
    stats: dict[str, int],
    progress: Callable[[int, int], None],
    key_clouds: dict[int, RefineCloud],
    first: str = "the sequence",
) -> _Tracked:
    key_cloud = load(0)
    if not refine_pairs.enough_points(key_cloud):
        raise RegistrationError(
            f"{first}: the first frame has fewer than {refine_pairs.MIN_PAIR_POINTS} points within "
            f"{config.max_depth:g} m at an ICP voxel of {config.voxel_size:g} m (check the depth "
            "scale, the maximum depth and the ICP voxel)"
        )
    key_clouds[0] = key_cloud
    tr = _Tracked([np.eye(4)], [0], [np.eye(4)], [0], [0], [], [], [1.0])
    velocity = np.eye(4)
    progress(1, num)
    for k in range(1, num):
        cloud = load(k)
        kf = tr.keyframes[-1]
        T_key_prev = np.linalg.inv(tr.poses[kf]) @ tr.poses[k - 1]
        usable = refine_pairs.enough_points(cloud)
        given = starts.motions[k]
        if usable:
            origin, est = _track(
                cloud, key_cloud, T_key_prev, velocity, starts.global_start, config, given
            )
        if usable and _fits(est, config):
            stats[f"start_{origin}"] += 1
            pose = tr.poses[kf] @ est.T_tgt_src
            velocity = np.linalg.inv(tr.poses[k - 1]) @ pose
            tr.reference.append(kf)
            tr.T_ref_frame.append(est.T_tgt_src)
            tr.fitness.append(est.fitness)
            new_key = _is_keyframe(est.T_tgt_src, est.fitness, config)
            segment = tr.segments[-1]
            if new_key:
                node = len(tr.keyframes)
                tr.edges.append(
                    posegraph.Edge(node, node - 1, est.T_tgt_src, est.information, False)
                )
        else:  # lost: keep moving as before, restart tracking from this frame if it can
            stats["lost"] += 1
            tr.lost.append(k)
            pose = tr.poses[k - 1] @ (velocity if given is None else given)
            tr.reference.append(kf)
            tr.T_ref_frame.append(np.linalg.inv(tr.poses[kf]) @ pose)
            tr.fitness.append(float("nan"))
            new_key, segment = usable, tr.segments[-1] + 1
        tr.poses.append(pose)
        if new_key:
            tr.keyframes.append(k)
            tr.segments.append(segment)
            tr.reference[k], tr.T_ref_frame[k] = k, np.eye(4)
            if config.pose_graph:  # the past keyframe is kept for loop edges: its levels only
                key_cloud.drop_points()
                key_clouds[k] = cloud
            key_cloud = cloud
        progress(k + 1, num)
    return tr


def _loop_edges(
    tr: _Tracked,
    key_clouds: dict[int, RefineCloud],
    config: OdometryConfig,
    stats: dict[str, int],
) -> list[posegraph.Edge]:
    """Loop edges between non-consecutive keyframes of a segment that are close in space."""
    poses = [tr.poses[k] for k in tr.keyframes]
    edges = []
    for b in range(len(poses)):
        near = []
        for a in range(b - 1):
            if tr.segments[a] != tr.segments[b]:
                continue
            rot, trans = posegraph.transform_difference(poses[a], poses[b])
            if trans < config.loop_max_distance and rot < config.loop_max_rotation_deg:
                near.append((trans, a))
        for _, a in sorted(near)[: config.loop_max_candidates]:
            stats["loops_tried"] += 1
            T_a_b = np.linalg.inv(poses[a]) @ poses[b]
            est = refine_pairs.refine_pair(
                key_clouds[tr.keyframes[b]], key_clouds[tr.keyframes[a]], T_a_b
            )
            if est.fitness >= config.loop_min_fitness and est.rmse <= config.max_rmse:
                edges.append(posegraph.Edge(b, a, est.T_tgt_src, est.information, True))
    return edges


def _optimise(tr: _Tracked, loops: list[posegraph.Edge], config: OdometryConfig, stats) -> None:
    """Optimise each segment's keyframe graph in place (re-anchored on its first keyframe)."""
    for segment in sorted(set(tr.segments)):
        nodes = [n for n, s in enumerate(tr.segments) if s == segment]
        local = {n: m for m, n in enumerate(nodes)}
        edges = [
            e._replace(src=local[e.src], tgt=local[e.tgt])
            for e in tr.edges + loops
            if e.src in local and e.tgt in local
        ]
        if len(nodes) < 2 or not any(e.uncertain for e in edges):
            continue
        initial = [tr.poses[tr.keyframes[n]] for n in nodes]
        optimised, kept = posegraph.optimize_pose_graph(
            initial, edges, refine_pairs.FINE_DISTANCE * config.voxel_size
        )
        anchor = initial[0] @ np.linalg.inv(optimised[0])
        for n, pose in zip(nodes, optimised, strict=True):
            tr.poses[tr.keyframes[n]] = anchor @ pose
        loop_kept = [k for e, k in zip(edges, kept, strict=True) if e.uncertain]
        stats["loops_kept"] += sum(loop_kept)
        stats["loops_pruned"] += len(loop_kept) - sum(loop_kept)


def estimate_trajectory(
    sequence: Any,
    config: OdometryConfig | None = None,
    global_start: GlobalStart | None = None,
    progress: Callable[[int, int], None] | None = None,
    given: list[np.ndarray | None] | None = None,
) -> Trajectory:
    """The camera trajectory of ``sequence`` by keyframe ICP odometry (see module doc).

    Args:
        sequence: an ``RGBDSequence`` (its poses are never read).
        config: settings.
        global_start: ``T_tgt_src`` of two frames' points (finest ICP voxel) when ICP from
            the motion prior fails; default FPFH + RANSAC.
        progress: called as ``progress(done, total)`` after each frame.
        given: a given trajectory's pose ``T_world_cam (4, 4)`` (any world) per frame of the
            sequence's frame list, or None where it has none: the motion between two used
            frames that both have one is where a frame's ICP starts (``stats``:
            ``start_init``).

    Returns:
        :class:`Trajectory`.

    Raises:
        FrameError: a depth image cannot be read.
        RegistrationError: the sequence has no frame, or the first has (almost) no depth.
        ValueError: ``given`` is not one entry per frame of the sequence.
    """
    config = config or OdometryConfig()
    report = progress or (lambda *_: None)
    frames = used_frames(len(sequence.frames), config)
    if not frames:
        raise RegistrationError("the sequence has no frame to track")
    timings = {"load": 0.0, "track": 0.0, "pose_graph": 0.0}

    def load(k: int) -> RefineCloud:
        start = time.perf_counter()
        points = frame_points(sequence, frames[k], config.max_depth)
        cloud = refine_pairs.pair_cloud(points, config.voxel_size)
        timings["load"] += time.perf_counter() - start
        return cloud

    if given is not None and len(given) != len(sequence.frames):
        raise ValueError(f"given: {len(given)} poses for {len(sequence.frames)} frames")
    motions = relative_motions(
        [None] * len(frames) if given is None else [given[f] for f in frames]
    )
    starts = _Starts(_global_start_of(global_start, config), motions)
    stats = dict.fromkeys(
        ["start_velocity", "start_previous", "start_global", "lost", "keyframes"], 0
    )
    if given is not None:
        stats["start_init"] = 0
    stats.update(loops_tried=0, loops_kept=0, loops_pruned=0)
    key_clouds: dict[int, RefineCloud] = {}
    started = time.perf_counter()
    first = str(sequence.frames[frames[0]].depth_path)
    tr = _tracking_pass(load, len(frames), starts, config, stats, report, key_clouds, first)
    timings["track"] = time.perf_counter() - started - timings["load"]
    stats["keyframes"] = len(tr.keyframes)
    if config.pose_graph and len(tr.keyframes) > 2:
        started = time.perf_counter()
        _optimise(tr, _loop_edges(tr, key_clouds, config, stats), config, stats)
        poses = [tr.poses[ref] @ T for ref, T in zip(tr.reference, tr.T_ref_frame, strict=True)]
        tr = tr._replace(poses=poses)
        timings["pose_graph"] = time.perf_counter() - started
    return Trajectory(
        frames=frames,
        poses=np.asarray(tr.poses, dtype=np.float64).reshape(-1, 4, 4),
        keyframes=tr.keyframes,
        lost=tr.lost,
        fitness=np.asarray(tr.fitness, dtype=np.float64),
        stats=stats,
        timings=timings,
    )


def config_dict(config: OdometryConfig) -> dict[str, Any]:
    """JSON-friendly settings."""
    return asdict(config)
