"""A whole scan: many overlapping clouds registered into one frame (``byoc register-scans``).

1. Every cloud's features are computed once (the extractor of ``byoc register``) and each cloud
   is prepared for ICP (:func:`byoc_cli.pipeline.refine_pairs.pair_cloud`).
2. Pairs: every pair ``i < j`` for small sets (``<= all_pairs_max`` clouds); for larger sets,
   the neighbours in the given order (``j - i <= neighbours``), then the CANDIDATE pairs: the
   other pairs whose coarse clouds overlap by at least ``candidate_overlap`` under the poses
   of a first pose graph of the neighbour edges.
3. Each pair is registered with the tool's pairwise registration
   (:func:`byoc_cli.pipeline.register.estimate_transform`, source ``j`` onto target ``i``),
   refined by the multiscale point-to-plane ICP of ``byoc register``
   (:func:`byoc_cli.pipeline.refine_pairs.refine_pair`; candidate pairs also from the first graph's
   relative pose, the better fit wins), and kept when the ICP fitness is at least
   ``min_fitness``.
4. A pose graph (node ``k`` = cloud ``k``, ``T_world_k``; edge ``(j, i)`` = ``T_i_j`` with
   its ICP information matrix): the maximum-fitness spanning tree gives the initial poses and
   the certain edges; every other kept pair is an uncertain (loop) edge that Open3D's global
   optimisation may prune. Clouds that no kept pair connects to cloud 0 are UNPLACED.

The world frame is cloud 0's. Transforms follow ``T_tgt_src`` (4x4 float64, column vectors).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import numpy as np
import torch

from byoc_cli.errors import RegistrationError, ShapeError, require_open3d
from byoc_cli.pipeline import posegraph, refine_pairs
from byoc_cli.pipeline.features import FeatureExtractor
from byoc_cli.pipeline.refine_levels import RefineCloud
from byoc_cli.pipeline.register import RegisterConfig, estimate_transform
from byoc_cli.threads import worker_pool


@dataclass(frozen=True)
class ScansConfig:
    """Settings of :func:`register_scans`.

    Attributes:
        all_pairs_max: up to this many clouds, every pair is tried.
        neighbours: larger sets: pairs ``(i, j)`` with ``0 < j - i <= neighbours``.
        candidate_overlap: larger sets: another pair is tried when at least this share of
            one coarse cloud lies near the other under the first graph's poses.
        icp_voxel: the finest ICP voxel (metres; the refinement's levels at 2.5, 1.25 and 1
            times it).
        min_fitness: a pair is kept when its ICP fitness (share of the source's points
            within 1.5 ICP voxels of the target) is at least this.
        edge_prune_threshold, preference_loop_closure: Open3D's global optimisation.
    """

    all_pairs_max: int = 20
    neighbours: int = 2
    candidate_overlap: float = 0.2
    icp_voxel: float = 0.02
    min_fitness: float = 0.3
    edge_prune_threshold: float = 0.25
    preference_loop_closure: float = 2.0

    def __post_init__(self) -> None:
        if self.all_pairs_max < 2 or self.neighbours < 1:
            raise ValueError("all_pairs_max must be >= 2 and neighbours >= 1")
        if self.icp_voxel <= 0 or not 0 <= self.min_fitness <= 1:
            raise ValueError("icp_voxel must be > 0 and min_fitness in [0, 1]")


class PairRecord(NamedTuple):
    """One pair tried.

    Attributes:
        i, j: target and source clouds (``i < j``).
        kind: ``"all"``, ``"neighbour"``, ``"candidate"`` or (from initial poses)
            ``"overlap"``.
        status: ``"kept"``, ``"rejected"`` (ICP fitness below the bar; from initial poses,
            or beyond the trust region) or ``"failed"`` (the pairwise registration raised;
            ``error`` says why).
        T_i_j: ``(4, 4)`` refined transform (maps cloud ``j`` into cloud ``i``), or None.
        information: ``(6, 6)`` ICP information matrix, or None.
        confidence: the pairwise registration's confidence (NaN when it failed).
        fitness, rmse: ICP fitness and inlier RMSE (NaN when it failed).
        edge: ``"tree"``, ``"loop"`` or ``""`` (not in the graph).
        pruned: True when the optimisation pruned this loop edge.
        seconds: time spent on the pair.
        error: the failure's message, else ``""``.
        init: from initial poses, ``T_init``, the ``correction`` and ``inside_trust_region``
            (:mod:`byoc_cli.pipeline.scans_init`); else None.
    """

    i: int
    j: int
    kind: str
    status: str
    T_i_j: np.ndarray | None
    information: np.ndarray | None
    confidence: float
    fitness: float
    rmse: float
    edge: str
    pruned: bool
    seconds: float
    error: str
    init: dict | None = None


class ScansResult(NamedTuple):
    """Result of :func:`register_scans`.

    Attributes:
        poses: per cloud, ``T_world_cloud (4, 4)`` (world = cloud 0), or None when unplaced.
        pairs: every pair tried, in the order tried.
        unplaced: clouds no kept pair connects to cloud 0.
        timings: seconds per stage.
    """

    poses: list[np.ndarray | None]
    pairs: list[PairRecord]
    unplaced: list[int]
    timings: dict[str, float]


class _PairSettings(NamedTuple):
    """What every pair's registration shares: the pairwise settings, the feature voxel and
    the keep bar."""

    register_config: RegisterConfig
    voxel_size: float
    min_fitness: float


def _register_pair(
    feats: list,
    clouds: list[RefineCloud],
    job: tuple[int, int, str, np.ndarray | None],
    settings: _PairSettings,
) -> PairRecord:
    """Pairwise registration of ``j`` onto ``i`` (``job``: ``i``, ``j``, the pair's kind and
    a prior ``T_i_j`` or None), ICP refinement, the keep decision."""
    i, j, kind, T_prior = job
    register_config, voxel_size, min_fitness = settings
    start = time.perf_counter()
    starts, confidence, error = [], float("nan"), ""
    try:
        result = estimate_transform(feats[j], feats[i], register_config, voxel_size)
        starts.append(result.T_tgt_src.numpy())
        confidence = result.confidence
    except RegistrationError as exc:
        error = str(exc)
    if T_prior is not None:
        starts.append(T_prior)
    if starts and not (
        refine_pairs.enough_points(clouds[i]) and refine_pairs.enough_points(clouds[j])
    ):
        starts, error = [], f"fewer than {refine_pairs.MIN_PAIR_POINTS} points at an ICP scale"
    if not starts:
        return PairRecord(
            i, j, kind, "failed", None, None, confidence, float("nan"), float("nan"), "",
            False, time.perf_counter() - start, error,
        )  # fmt: skip
    est = max(
        (refine_pairs.refine_pair(clouds[j], clouds[i], T) for T in starts),
        key=lambda e: (e.fitness, -e.rmse),
    )
    status = "kept" if est.fitness >= min_fitness else "rejected"
    return PairRecord(
        i, j, kind, status, est.T_tgt_src, est.information, confidence, est.fitness, est.rmse,
        "", False, time.perf_counter() - start, "",
    )  # fmt: skip


def _spanning_tree(num: int, pairs: list[PairRecord]) -> tuple[list[np.ndarray | None], set]:
    """Poses from the maximum-fitness spanning tree of the kept pairs grown from cloud 0.

    Returns:
        ``(poses, tree)``: ``T_world_k`` per cloud (None when not reached) and the positions
        in ``pairs`` of the tree's edges.
    """
    poses: list[np.ndarray | None] = [None] * num
    poses[0] = np.eye(4)
    tree: set[int] = set()
    kept = [(n, p) for n, p in enumerate(pairs) if p.status == "kept"]
    while True:  # Prim: the best edge from the tree to a new cloud
        best = None
        for n, p in kept:
            if (poses[p.i] is None) == (poses[p.j] is None):
                continue
            if best is None or p.fitness > best[1].fitness:
                best = (n, p)
        if best is None:
            return poses, tree
        n, p = best
        if poses[p.j] is None:
            poses[p.j] = poses[p.i] @ p.T_i_j
        else:
            poses[p.i] = poses[p.j] @ np.linalg.inv(p.T_i_j)
        tree.add(n)


def _optimise(
    pairs: list[PairRecord], config: ScansConfig, num: int, start: list | None = None
) -> tuple[list[np.ndarray | None], list[PairRecord]]:
    """The pose graph of the kept pairs (module doc, step 4); pairs get ``edge``/``pruned``.
    ``start``: ``T_world_k`` per cloud (world = cloud 0) where the optimisation starts, in
    place of the spanning tree's poses (:mod:`byoc_cli.pipeline.scans_init`)."""
    initial, tree = _spanning_tree(num, pairs)
    placed = [k for k in range(num) if initial[k] is not None]
    local = {k: m for m, k in enumerate(placed)}
    in_graph = [
        n for n, p in enumerate(pairs) if p.status == "kept" and p.i in local and p.j in local
    ]
    pairs = list(pairs)
    for n in in_graph:
        pairs[n] = pairs[n]._replace(edge="tree" if n in tree else "loop")
    if len(placed) < 2 or len(in_graph) == len(tree):  # a tree alone: nothing to optimise
        return initial, pairs
    edges = [
        posegraph.Edge(
            local[pairs[n].j], local[pairs[n].i], pairs[n].T_i_j, pairs[n].information,
            n not in tree,
        )
        for n in in_graph
    ]  # fmt: skip
    optimised, kept = posegraph.optimize_pose_graph(
        [(initial if start is None else start)[k] for k in placed],
        edges,
        refine_pairs.FINE_DISTANCE * config.icp_voxel,
        edge_prune_threshold=config.edge_prune_threshold,
        preference_loop_closure=config.preference_loop_closure,
    )
    anchor = np.linalg.inv(optimised[0])  # cloud 0 stays the world
    poses: list[np.ndarray | None] = [None] * num
    for k, pose in zip(placed, optimised, strict=True):
        poses[k] = anchor @ pose
    poses[0] = np.eye(4)
    for n, survived in zip(in_graph, kept, strict=True):
        pairs[n] = pairs[n]._replace(pruned=not survived)
    return poses, pairs


#: candidate pairs: a coarse point overlaps when another cloud's coarse points lie within
#: this many finest ICP voxels
CANDIDATE_RADIUS = 6.0


def _candidates(
    clouds: list[RefineCloud],
    poses: list[np.ndarray | None],
    tried: set[tuple[int, int]],
    min_overlap: float,
) -> list[tuple[int, int]]:
    """Untried pairs whose coarse clouds overlap by at least ``min_overlap`` under ``poses``."""
    o3d = require_open3d()
    radius = CANDIDATE_RADIUS * refine_pairs.icp_voxel(clouds[0])
    world = {}
    for k, pose in enumerate(poses):
        if pose is not None:
            coarse = clouds[k].average(0).numpy()
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(coarse))
            world[k] = cloud.transform(pose)
    out = []
    for i in sorted(world):
        for j in sorted(world):
            if j <= i or (i, j) in tried:
                continue
            distances = np.asarray(world[j].compute_point_cloud_distance(world[i]))
            if len(distances) and float(np.mean(distances < radius)) >= min_overlap:
                out.append((i, j))
    return out


def register_scans(
    points: Sequence[np.ndarray],
    extractor: FeatureExtractor,
    register_config: RegisterConfig | None = None,
    config: ScansConfig | None = None,
    labels: Sequence[str] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    workers: int = 1,
) -> ScansResult:
    """Register ``points`` (a list of ``(N_k, 3)`` clouds in metres) into cloud 0's frame.

    Args:
        points: the clouds, at least 2.
        extractor: the feature extractor of the pairwise registration.
        register_config: the pairwise registration's settings.
        config: settings of the pairs and the pose graph.
        labels: how errors name each cloud (its file name in the CLI).
        progress: called as ``progress(stage, done, total)``.
        workers: threads that encode and prepare clouds and register pairs side by side,
            one torch thread each (:func:`byoc_cli.threads.worker_pool`); the results do
            not depend on it.

    Returns:
        :class:`ScansResult`.

    Raises:
        ShapeError: fewer than 2 clouds, or one is not ``(N, 3)``.
        RegistrationError: a cloud has fewer than 3 voxels or is degenerate for the features.
    """
    config = config or ScansConfig()
    register_config = register_config or RegisterConfig()
    report = progress or (lambda *_: None)
    arrays, labels = checked_clouds(points, labels)
    timings = {"features": 0.0, "prepare": 0.0, "pairs": 0.0, "pose_graph": 0.0}
    pool = worker_pool(workers)
    try:
        return _register_all(
            arrays, extractor, register_config, config, labels, report, timings, pool
        )
    finally:
        pool.shutdown(cancel_futures=True)


def checked_clouds(points: Sequence, labels: Sequence[str] | None) -> tuple[list, list[str]]:
    """``points`` as ``(N_k, 3)`` float64 arrays and the labels (default ``cloud k``).

    Raises:
        ShapeError: fewer than 2 clouds, or one is not ``(N, 3)``.
    """
    labels = list(labels) if labels is not None else [f"cloud {k}" for k in range(len(points))]
    if len(points) < 2:
        raise ShapeError(f"need at least 2 clouds, got {len(points)}")
    arrays = [np.asarray(cloud, dtype=np.float64) for cloud in points]
    for k, cloud in enumerate(arrays):
        if cloud.ndim != 2 or cloud.shape[1] != 3:
            raise ShapeError(f"{labels[k]}: points must be (N, 3), got {cloud.shape}")
    return arrays, labels


def _register_all(arrays, extractor, register_config, config, labels, report, timings, pool):
    """:func:`register_scans` once its inputs are checked, on the worker ``pool``."""
    num = len(arrays)

    def prepare(k: int):
        start = time.perf_counter()
        feats = extractor(torch.from_numpy(arrays[k]), label=labels[k])
        mid = time.perf_counter()
        cloud = refine_pairs.pair_cloud(arrays[k], config.icp_voxel).prepare()
        return feats, cloud, mid - start, time.perf_counter() - mid

    feats, clouds = [], []
    for k, (f, cloud, t_features, t_prepare) in enumerate(pool.map(prepare, range(num))):
        feats.append(f)
        clouds.append(cloud)
        timings["features"] += t_features
        timings["prepare"] += t_prepare
        report("features", k + 1, num)

    settings = _PairSettings(register_config, extractor.voxel_size, config.min_fitness)

    def pair(job: tuple[int, int, str, np.ndarray | None]) -> PairRecord:
        return _register_pair(feats, clouds, job, settings)

    def run(todo: list[tuple[int, int]], kind: str, poses=None) -> list[PairRecord]:
        done = []
        start = time.perf_counter()
        jobs = [
            (i, j, kind, None if poses is None else np.linalg.inv(poses[i]) @ poses[j])
            for i, j in todo
        ]
        for n, record in enumerate(pool.map(pair, jobs)):
            done.append(record)
            report(f"{kind} pairs", n + 1, len(todo))
        timings["pairs"] += time.perf_counter() - start
        return done

    if num <= config.all_pairs_max:
        pairs = run([(i, j) for i in range(num) for j in range(i + 1, num)], "all")
    else:
        todo = [
            (i, j) for i in range(num) for j in range(i + 1, min(num, i + config.neighbours + 1))
        ]
        pairs = run(todo, "neighbour")
        start = time.perf_counter()
        first, _ = _optimise(pairs, config, num)
        candidates = _candidates(clouds, first, set(todo), config.candidate_overlap)
        timings["pose_graph"] += time.perf_counter() - start
        pairs += run(candidates, "candidate", first)
    start = time.perf_counter()
    poses, pairs = _optimise(pairs, config, num)
    timings["pose_graph"] += time.perf_counter() - start
    unplaced = [k for k in range(num) if poses[k] is None]
    return ScansResult(poses, pairs, unplaced, timings)


def merge_clouds(
    points: Sequence[np.ndarray], poses: Sequence[np.ndarray | None], voxel_size: float
) -> np.ndarray:
    """The clouds placed by ``poses`` (None: left out), merged and voxel-downsampled.

    Args:
        points: ``(N_k, 3)`` clouds.
        poses: ``T_world_k (4, 4)`` per cloud, or None.
        voxel_size: Open3D voxel-centroid downsampling, metres.

    Returns:
        ``(M, 3)`` float64 points in the world frame.
    """
    o3d = require_open3d()
    placed = [
        np.asarray(p, np.float64) @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]
        for p, T in zip(points, poses, strict=True)
        if T is not None
    ]
    if not placed:
        return np.zeros((0, 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(placed)))
    return np.asarray(cloud.voxel_down_sample(voxel_size).points)


def config_dict(config: ScansConfig) -> dict[str, Any]:
    """JSON-friendly settings."""
    return asdict(config)
