"""``register-scans`` from initial poses (``--init-poses``, an E57 file's stored poses).

Given a guess of ``T_world_k`` per cloud (a trajectory: odometry, a robot, GNSS/IMU, a
scanner's stations), no features are computed:

1. each cloud is prepared for the refinement of ``register-scans``
   (:func:`~byoc_cli.pipeline.refine_pairs.pair_cloud`) and, from its coarsest level, for the
   coarse pass of the local registration (:data:`~byoc_cli.pipeline.local.COARSE_BASE`
   refinement voxels);
2. PAIRS: every pair ``i < j`` whose coarse clouds overlap under the poses: at least
   ``candidate_overlap`` of either cloud lies within ``CANDIDATE_RADIUS`` finest ICP voxels of
   the other (the test of ``register-scans``' candidate pairs, both ways);
3. each pair is registered from ``T_i_j = inv(P_i) @ P_j`` (source ``j``, target ``i``) as
   :func:`~byoc_cli.pipeline.local.register_local` does: the coarse plane-to-plane pass
   (:func:`~byoc_cli.pipeline.local.align_coarse`), then the refinement of ``register-scans``
   (:func:`~byoc_cli.pipeline.refine_pairs.refine_pair`, which also gives the fitness and the
   information matrix of a pose-graph edge): from the coarse pass's end and from the guess
   itself on :data:`~byoc_cli.pipeline.local.PROBE_POINTS` source points a level, the
   guess's kept unless the other ends elsewhere and fits better by
   :data:`~byoc_cli.pipeline.local.SWITCH_FITNESS`, then refined again on all points (up to
   20000 a level) from the one kept. The pair is KEPT when its fitness reaches
   ``min_fitness`` and its correction from the guess lies inside the trust region
   (:class:`~byoc_cli.pipeline.local.TrustRegion`; default 20 deg and 20 refinement voxels,
   50 finest ICP voxels: 1 m at ``icp_voxel`` 2 cm); else it is rejected, not an edge;
4. the pose graph of :func:`~byoc_cli.pipeline.scans.register_scans` over the kept pairs,
   optimised from the poses (relative to cloud 0). A cloud no kept pair connects to cloud 0 is
   UNPLACED: its pose was never confirmed.

The world frame is cloud 0's, as without poses. Transforms ``T_tgt_src``, 4x4 float64.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.sampling import local_frame
from byoc_cli.pipeline import refine_pairs
from byoc_cli.pipeline.local import (
    COARSE_BASE,
    PROBE_POINTS,
    SAME_DEG,
    SAME_VOXELS,
    SWITCH_FITNESS,
    TrustRegion,
    align_coarse,
    correction,
)
from byoc_cli.pipeline.posegraph import transform_difference
from byoc_cli.pipeline.refine import refine_multiscale
from byoc_cli.pipeline.refine_levels import RefineCloud
from byoc_cli.pipeline.scans import (
    CANDIDATE_RADIUS,
    PairRecord,
    ScansConfig,
    ScansResult,
    _optimise,
    checked_clouds,
)
from byoc_cli.threads import worker_pool


class _Prepared(NamedTuple):
    """Per cloud: its refinement cloud, its coarse cloud and its centroid; the trust region
    in the clouds' units; the keep bar."""

    fine: list[RefineCloud]
    coarse: list[RefineCloud]
    centroids: list[np.ndarray]
    trust: TrustRegion
    min_fitness: float


def register_scans_from_poses(
    points: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    config: ScansConfig | None = None,
    trust: TrustRegion | None = None,
    labels: Sequence[str] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    workers: int = 1,
) -> ScansResult:
    """Register ``points`` (``(N_k, 3)`` clouds, metres) into cloud 0's frame from ``poses``
    (a guess of ``T_world_k (4, 4)`` per cloud, any world), as the module doc says.

    Args:
        trust: the trust region of each pair (translation in the clouds' units; None: the
            default, 20 refinement voxels).
        workers: threads that prepare clouds and register pairs side by side.
        the others: as :func:`~byoc_cli.pipeline.scans.register_scans`.

    Returns:
        :class:`~byoc_cli.pipeline.scans.ScansResult`; its pairs have ``kind`` ``"overlap"``
        and ``init``; ``timings`` has ``features`` 0.

    Raises:
        ShapeError: fewer than 2 clouds, one not ``(N, 3)``, or not one ``(4, 4)`` finite
            pose per cloud.
    """
    config = config or ScansConfig()
    report = progress or (lambda *_: None)
    arrays, labels = checked_clouds(points, labels)
    given = np.asarray(poses, dtype=np.float64)
    if given.shape != (len(arrays), 4, 4) or not np.isfinite(given).all():
        raise ShapeError(f"need one finite (4, 4) pose per cloud: {given.shape}, {len(arrays)}")
    start = [np.linalg.inv(given[0]) @ pose for pose in given]  # world = cloud 0
    start[0] = np.eye(4)
    timings = {"features": 0.0, "prepare": 0.0, "pairs": 0.0, "pose_graph": 0.0}
    pool = worker_pool(workers)
    try:
        began = time.perf_counter()

        def prepare(k: int) -> RefineCloud:
            cloud = refine_pairs.pair_cloud(arrays[k], config.icp_voxel).prepare()
            report("prepare", k + 1, len(arrays))
            return cloud

        fine = list(pool.map(prepare, range(len(arrays))))
        voxel = fine[0].voxel_size
        coarse = [RefineCloud(c.average(0), COARSE_BASE * voxel, pyramid=True) for c in fine]
        centroids = [local_frame(a).centroid(a) for a in arrays]  # strays left out
        region = (trust or TrustRegion()).resolved(voxel, 1.0)
        prepared = _Prepared(fine, coarse, centroids, region, config.min_fitness)
        todo = overlapping_pairs(fine, start, config.candidate_overlap)
        timings["prepare"] = time.perf_counter() - began

        def pair(job: tuple[int, int]) -> PairRecord:
            i, j = job
            return register_pair_from(prepared, i, j, np.linalg.inv(start[i]) @ start[j])

        began = time.perf_counter()
        pairs = []
        for n, record in enumerate(pool.map(pair, todo)):
            pairs.append(record)
            report("overlap pairs", n + 1, len(todo))
        timings["pairs"] = time.perf_counter() - began
    finally:
        pool.shutdown(cancel_futures=True)
    began = time.perf_counter()
    placed, pairs = _optimise(pairs, config, len(arrays), start)
    timings["pose_graph"] = time.perf_counter() - began
    unplaced = [k for k in range(len(arrays)) if placed[k] is None]
    return ScansResult(placed, pairs, unplaced, timings)


def overlapping_pairs(
    clouds: list[RefineCloud], poses: Sequence[np.ndarray], min_overlap: float
) -> list[tuple[int, int]]:
    """The pairs ``(i, j)``, ``i < j``, of which at least ``min_overlap`` of either coarse
    cloud (level 0) lies within ``CANDIDATE_RADIUS`` finest ICP voxels of the other under
    ``poses`` (``T_world_k``)."""
    from pykdtree.kdtree import KDTree

    radius = CANDIDATE_RADIUS * refine_pairs.icp_voxel(clouds[0])
    world = []
    for cloud, pose in zip(clouds, poses, strict=True):
        coarse = cloud.average(0).numpy()
        world.append(np.ascontiguousarray(coarse @ pose[:3, :3].T + pose[:3, 3]))
    trees = [KDTree(points) if len(points) else None for points in world]

    def share(a: int, b: int) -> float:
        """The share of cloud ``a`` within the radius of cloud ``b``."""
        if trees[b] is None or not len(world[a]):
            return 0.0
        distances, _ = trees[b].query(world[a], k=1, distance_upper_bound=radius)
        return float(np.mean(np.isfinite(distances)))

    return [
        (i, j)
        for i in range(len(clouds))
        for j in range(i + 1, len(clouds))
        if max(share(i, j), share(j, i)) >= min_overlap
    ]


def register_pair_from(prepared: _Prepared, i: int, j: int, T_guess: np.ndarray) -> PairRecord:
    """Cloud ``j`` onto cloud ``i`` from ``T_guess (4, 4)`` (module doc, step 3)."""
    start = time.perf_counter()
    fine, coarse = prepared.fine, prepared.coarse
    if not (refine_pairs.enough_points(fine[i]) and refine_pairs.enough_points(fine[j])):
        error = f"fewer than {refine_pairs.MIN_PAIR_POINTS} points at an ICP scale"
        return PairRecord(
            i, j, "overlap", "failed", None, None, float("nan"), float("nan"), float("nan"),
            "", False, time.perf_counter() - start, error,
        )  # fmt: skip
    T_coarse, _ = align_coarse(coarse[j], coarse[i], torch.from_numpy(T_guess))
    voxel = fine[j].voxel_size
    far, near = (
        refine_multiscale(fine[j], fine[i], T, voxel, max_source_points=PROBE_POINTS)
        for T in (T_coarse, torch.from_numpy(T_guess))
    )
    degrees, distance = transform_difference(near.T_tgt_src.numpy(), far.T_tgt_src.numpy())
    same = degrees < SAME_DEG and distance < SAME_VOXELS * voxel
    chosen = near if not same and far.fitness <= near.fitness + SWITCH_FITNESS else far
    est = refine_pairs.refine_pair(fine[j], fine[i], chosen.T_tgt_src.numpy())
    moved = correction(est.T_tgt_src, T_guess, prepared.centroids[j])
    inside = prepared.trust.holds(moved)
    kept = inside and est.fitness >= prepared.min_fitness
    init = {"T_init": T_guess.tolist(), "correction": moved.as_dict()}
    init["inside_trust_region"] = inside
    return PairRecord(
        i, j, "overlap", "kept" if kept else "rejected", est.T_tgt_src, est.information,
        float("nan"), est.fitness, est.rmse, "", False, time.perf_counter() - start, "", init,
    )  # fmt: skip
