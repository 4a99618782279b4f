"""Pose graphs over many clouds and FPFH + RANSAC starts (Open3D, imported lazily).

Shared by the self-posed training pairs (``byoc_cli.training.pseudo_poses``), ``odometry``
and ``register-scans``. The pairs of ``odometry`` and ``register-scans`` are refined by
:func:`byoc_cli.pipeline.refine_pairs.refine_pair`; the self-posed pairs by Open3D's multi-scale ICP
(:func:`multiscale_icp`, below). Clouds are ``(N, 3)`` float numpy arrays in
metres. Transforms follow the package convention: ``T_tgt_src`` is ``(4, 4)`` float64 on
column vectors. A
pose graph holds ``T_world_node`` per node; an edge ``(s, t)`` carries ``T_t_s`` (maps node
``s`` into node ``t``) and a 6x6 information matrix (Open3D's order: rotation, translation).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from byoc_cli.errors import require_open3d
from byoc_cli.fitting.ransac import CONFIDENCE, MAX_ITERATIONS

#: normals from at most this many neighbours within 2 voxels (FPFH's cloud)
NORMAL_MAX_NN = 30
#: FPFH + RANSAC runs at this multiple of the finest ICP voxel
FPFH_VOXEL_FACTOR = 4.0


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of the rotation ``R (3, 3)`` in degrees."""
    cos = (np.trace(R) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


def transform_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Rotation (deg) and translation (m) of ``inv(T_a) @ T_b``."""
    delta = np.linalg.inv(T_a) @ T_b
    return rotation_angle_deg(delta[:3, :3]), float(np.linalg.norm(delta[:3, 3]))


def _fpfh_cloud(points: np.ndarray, size: float):
    """``points (N, 3)`` voxel-downsampled at ``size`` with normals (Open3D)."""
    o3d = require_open3d()
    base = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    cloud = base.voxel_down_sample(size)
    cloud.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * size, max_nn=NORMAL_MAX_NN)
    )
    return cloud


def fpfh_ransac(
    points_src: np.ndarray, points_tgt: np.ndarray, icp_voxel: float, seed: int = 0
) -> np.ndarray:
    """Global FPFH + RANSAC (Open3D) of ``points_src (N, 3)`` onto ``points_tgt (M, 3)`` at
    ``FPFH_VOXEL_FACTOR`` times the finest ICP voxel; returns ``T_tgt_src``."""
    size = FPFH_VOXEL_FACTOR * icp_voxel
    clouds = [_fpfh_cloud(points, size) for points in (points_src, points_tgt)]
    return _fpfh_ransac_clouds(clouds[0], clouds[1], size, seed)


def _fpfh_ransac_clouds(src, tgt, size: float, seed: int) -> np.ndarray:
    """FPFH + RANSAC of two Open3D clouds with normals, voxelised at ``size``."""
    o3d = require_open3d()
    reg = o3d.pipelines.registration
    feats = [
        reg.compute_fpfh_feature(
            cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * size, max_nn=100)
        )
        for cloud in (src, tgt)
    ]
    o3d.utility.random.seed(seed)
    result = reg.registration_ransac_based_on_feature_matching(
        src,
        tgt,
        feats[0],
        feats[1],
        True,
        1.5 * size,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [
            reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            reg.CorrespondenceCheckerBasedOnDistance(1.5 * size),
        ],
        reg.RANSACConvergenceCriteria(MAX_ITERATIONS, CONFIDENCE),
    )
    return np.asarray(result.transformation).copy()


# ------------------------------------------------ the self-posed training pairs' ICP (Open3D)
# The self-posed pairs keep Open3D's multi-scale ICP: with the refinement of ``byoc
# register`` (``refine_pairs.refine_pair``) the wide pairs of tum_fr1_desk_full measured worse
# (gaps of 40 and 60 frames: 19 and 3 pairs kept instead of 32 and 28, median rotation
# error 3.2 and 4.1 deg instead of 1.9 and 2.0; CHANGELOG).

#: ICP scales as multiples of the fine voxel: (voxel factor, correspondence distance factor)
ICP_SCALES = ((4.0, 6.0), (2.0, 3.0), (1.0, 1.5))
ICP_ITERATIONS = (30, 30, 30)


class PreparedCloud(NamedTuple):
    """One cloud at the ICP scales: ``levels[k]`` is an Open3D cloud with normals."""

    levels: list[Any]
    voxel_size: float


class PairEstimate(NamedTuple):
    """An ICP result.

    Attributes:
        T_tgt_src: ``(4, 4)`` float64.
        fitness: share of source points with a target point within the finest distance.
        rmse: RMS distance of those inlier pairs (metres).
        information: ``(6, 6)`` Open3D information matrix at the finest distance.
    """

    T_tgt_src: np.ndarray
    fitness: float
    rmse: float
    information: np.ndarray


def prepare_cloud(points: np.ndarray, voxel_size: float) -> PreparedCloud:
    """Voxel-downsample ``points (N, 3)`` at each ICP scale and estimate normals."""
    o3d = require_open3d()
    base = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    levels = []
    for voxel_factor, _ in ICP_SCALES:
        size = voxel_factor * voxel_size
        cloud = base.voxel_down_sample(size)
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * size, max_nn=NORMAL_MAX_NN)
        )
        levels.append(cloud)
    return PreparedCloud(levels, float(voxel_size))


def multiscale_icp(src: PreparedCloud, tgt: PreparedCloud, T_init: np.ndarray) -> PairEstimate:
    """Coarse-to-fine point-to-plane ICP of ``src`` onto ``tgt`` from ``T_init (4, 4)``."""
    o3d = require_open3d()
    reg = o3d.pipelines.registration
    T = np.asarray(T_init, np.float64)
    result = None
    for level, ((_, dist_factor), iters) in enumerate(zip(ICP_SCALES, ICP_ITERATIONS, strict=True)):
        dist = dist_factor * src.voxel_size
        result = reg.registration_icp(
            src.levels[level],
            tgt.levels[level],
            dist,
            T,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=iters),
        )
        T = np.asarray(result.transformation)
    dist = ICP_SCALES[-1][1] * src.voxel_size
    info = reg.get_information_matrix_from_point_clouds(src.levels[-1], tgt.levels[-1], dist, T)
    return PairEstimate(
        T.copy(), float(result.fitness), float(result.inlier_rmse), np.asarray(info)
    )


def prepared_fpfh_ransac(src: PreparedCloud, tgt: PreparedCloud, seed: int = 0) -> np.ndarray:
    """Global FPFH + RANSAC (Open3D, on the coarsest ICP level); returns ``T_tgt_src``."""
    size = ICP_SCALES[0][0] * src.voxel_size
    return _fpfh_ransac_clouds(src.levels[0], tgt.levels[0], size, seed)


class Edge(NamedTuple):
    """A pose-graph edge: ``T_tgt_src`` maps node ``src`` into node ``tgt``."""

    src: int
    tgt: int
    T_tgt_src: np.ndarray
    information: np.ndarray
    uncertain: bool


def optimize_pose_graph(
    poses: list[np.ndarray],
    edges: list[Edge],
    max_correspondence_distance: float,
    *,
    edge_prune_threshold: float = 0.25,
    preference_loop_closure: float = 0.1,
) -> tuple[list[np.ndarray], list[bool]]:
    """Globally optimise node poses with Open3D (Levenberg-Marquardt, pruning bad edges).

    Args:
        poses: initial ``T_world_node (4, 4)`` per node (node 0 is the reference).
        edges: odometry edges (``uncertain=False``) and loop edges (``True``).
        max_correspondence_distance: the ICP distance the information matrices used.
        edge_prune_threshold: Open3D's line-process threshold for pruning loop edges.
        preference_loop_closure: Open3D's weight of loop edges against odometry.

    Returns:
        ``(poses, kept)``: optimised ``T_world_node`` per node and, per input edge, whether
        the optimisation kept it (odometry edges are always kept).
    """
    o3d = require_open3d()
    reg = o3d.pipelines.registration
    graph = reg.PoseGraph()
    for pose in poses:
        graph.nodes.append(reg.PoseGraphNode(np.asarray(pose, np.float64)))
    for edge in edges:
        # Open3D's edge (s, t) holds the transform that maps node s into node t
        graph.edges.append(
            reg.PoseGraphEdge(
                edge.src,
                edge.tgt,
                np.asarray(edge.T_tgt_src, np.float64),
                np.asarray(edge.information, np.float64),
                uncertain=edge.uncertain,
            )
        )
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=max_correspondence_distance,
        edge_prune_threshold=edge_prune_threshold,
        preference_loop_closure=preference_loop_closure,
        reference_node=0,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(
            graph,
            reg.GlobalOptimizationLevenbergMarquardt(),
            reg.GlobalOptimizationConvergenceCriteria(),
            option,
        )
    kept_keys = {(e.source_node_id, e.target_node_id) for e in graph.edges}
    kept = [(e.src, e.tgt) in kept_keys for e in edges]
    return [np.asarray(node.pose).copy() for node in graph.nodes], kept
