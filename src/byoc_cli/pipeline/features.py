"""Per-cloud feature extractors: the learned geometric encoder (``byoc``) and FPFH.

Both voxelise the input with :func:`byoc_cli.geometry.voxelize` (first point per voxel)
and return one unit-norm feature per kept point, so that matching, fitting and the
metrics see exactly the same points whichever features are used.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import torch

from byoc_cli.errors import RegistrationError
from byoc_cli.geometry import voxelize

MIN_POINTS = 3

#: Open3D tutorial radii for FPFH, as multiples of the voxel size.
FPFH_NORMAL_RADIUS = 2.0
FPFH_FEATURE_RADIUS = 5.0
FPFH_NORMAL_MAX_NN = 30
FPFH_FEATURE_MAX_NN = 100


class CloudFeatures(NamedTuple):
    """Features of one cloud.

    Attributes:
        points: ``(M, 3)`` float64 kept points (original xyz of the first point per voxel).
        feats: ``(M, C)`` float32 L2-normalised features, ``feats[m]`` describes ``points[m]``.
        point_index: ``(M,)`` int64; ``points[m]`` is input point ``point_index[m]``.
        coords: ``(M, 3)`` int64 voxel coordinates.
    """

    points: torch.Tensor
    feats: torch.Tensor
    point_index: torch.Tensor
    coords: torch.Tensor


class FeatureExtractor(Protocol):
    """Anything that turns ``points (N, 3)`` into :class:`CloudFeatures`."""

    name: str
    voxel_size: float

    def __call__(self, points: torch.Tensor) -> CloudFeatures: ...


def _voxelize_checked(points: torch.Tensor, voxel_size: float, label: str):
    grid = voxelize(points, voxel_size)
    if grid.point_index.numel() < MIN_POINTS:
        raise RegistrationError(
            f"{label}: only {grid.point_index.numel()} voxel(s) at voxel size {voxel_size} m "
            f"(need at least {MIN_POINTS}); is the voxel size or the unit right?"
        )
    return grid


class ByocExtractor:
    """The frozen geometric encoder on a voxelised cloud.

    Args:
        encoder: a :class:`byoc_cli.models.encoder.GeometricEncoder`; moved to ``device``
            and put in eval mode.
        voxel_size: in the units of the points (metres).
        device: where the encoder runs.
    """

    name = "byoc"

    def __init__(self, encoder: torch.nn.Module, voxel_size: float, device: str = "cpu") -> None:
        self.encoder = encoder.to(device).eval()
        self.voxel_size = float(voxel_size)
        self.device = torch.device(device)

    def __call__(self, points: torch.Tensor, label: str = "cloud") -> CloudFeatures:
        from byoc_cli.models.encoder import encode_voxels

        grid = _voxelize_checked(points, self.voxel_size, label)
        with torch.inference_mode():
            feats = encode_voxels(self.encoder, grid.coords.to(self.device)).float().cpu()
        kept = points[grid.point_index].to(torch.float64)
        return CloudFeatures(kept, feats, grid.point_index, grid.coords)


class FpfhExtractor:
    """Open3D FPFH (33-d) on the voxelised cloud, normals and radii as in Open3D's tutorial.

    The histograms are L2-normalised so that the same cosine matcher applies.
    """

    name = "fpfh"

    def __init__(self, voxel_size: float) -> None:
        self.voxel_size = float(voxel_size)

    def __call__(self, points: torch.Tensor, label: str = "cloud") -> CloudFeatures:
        from byoc_cli.errors import require_open3d

        o3d = require_open3d()
        grid = _voxelize_checked(points, self.voxel_size, label)
        kept = points[grid.point_index].to(torch.float64)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kept.numpy()))
        pcd.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=FPFH_NORMAL_RADIUS * self.voxel_size, max_nn=FPFH_NORMAL_MAX_NN
            )
        )
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pcd,
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=FPFH_FEATURE_RADIUS * self.voxel_size, max_nn=FPFH_FEATURE_MAX_NN
            ),
        )
        feats = torch.from_numpy(np.ascontiguousarray(np.asarray(fpfh.data).T, dtype=np.float32))
        feats = torch.nn.functional.normalize(feats, dim=1)
        return CloudFeatures(kept, feats, grid.point_index, grid.coords)
