"""The classical ICP baselines of the comparison (``icp-point`` / ``icp-plane``): Open3D's ICP
from the identity on clouds voxelised at :data:`ICP_VOXEL_SIZE`, correspondences up to
:data:`ICP_MAX_DISTANCE`, at most :data:`ICP_MAX_ITERATION` iterations.
"""

from __future__ import annotations

import torch

from byoc_cli.geometry import voxelize

__all__ = ["ICP_MAX_DISTANCE", "ICP_MAX_ITERATION", "ICP_VOXEL_SIZE", "icp_points", "open3d_icp"]

#: ICP input voxel size (m).
ICP_VOXEL_SIZE = 0.025
#: ICP's largest correspondence distance (m).
ICP_MAX_DISTANCE = 0.10
#: ICP iterations at most.
ICP_MAX_ITERATION = 50


def open3d_icp(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    T_init: torch.Tensor,
    max_distance: float,
    *,
    point_to_plane: bool = True,
    max_iteration: int = ICP_MAX_ITERATION,
) -> torch.Tensor:
    """Open3D's ICP from ``T_init``, the classical baselines ``icp-point`` and ``icp-plane``;
    returns the refined ``T_tgt_src``.

    Args:
        points_src, points_tgt: ``(N, 3)`` and ``(M, 3)`` points.
        T_init: ``(4, 4)`` initial ``T_tgt_src``.
        max_distance: largest correspondence distance, in the units of the points.
        point_to_plane: point-to-plane (target normals from 30 neighbours within
            ``2 * max_distance``); False: point-to-point.
        max_iteration: ICP iterations at most.
    """
    from byoc_cli.errors import require_open3d

    o3d = require_open3d()
    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_src.double().numpy()))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_tgt.double().numpy()))
    if point_to_plane:
        tgt.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=2 * max_distance, max_nn=30)
        )
        estimation = reg.TransformationEstimationPointToPlane()
    else:
        estimation = reg.TransformationEstimationPointToPoint()
    out = reg.registration_icp(
        src,
        tgt,
        max_distance,
        T_init.double().numpy(),
        estimation,
        reg.ICPConvergenceCriteria(max_iteration=max_iteration),
    )
    return torch.from_numpy(out.transformation.copy()).to(torch.float64)


def icp_points(points: torch.Tensor) -> torch.Tensor:
    """The ICP input: ``points (N, 3)`` voxelised at :data:`ICP_VOXEL_SIZE` (first point)."""
    grid = voxelize(points, ICP_VOXEL_SIZE)
    return points[grid.point_index].to(torch.float64)
