"""Per-cloud feature extractors: the learned geometric encoder (``byoc``) and FPFH.

Both voxelise the input with :func:`byoc_cli.geometry.voxelize` (first point per voxel)
and return one unit-norm feature per kept point, so that matching, fitting and the
metrics see exactly the same points whichever features are used.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np
import torch

from byoc_cli.errors import RegistrationError, ShapeError
from byoc_cli.geometry import voxelize

MIN_POINTS = 3
#: A cloud whose kept points lie within this many voxel sizes of one line is collinear: the
#: features cannot see across it, and the rotation about the line is not determined.
COLLINEAR_SPREAD = 0.1

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

    def __call__(
        self, points: torch.Tensor, label: str = "cloud", voxel_size: float | None = None
    ) -> CloudFeatures: ...


def _voxelize_checked(points: torch.Tensor, voxel_size: float, label: str):
    """Voxelise, refusing what cannot be registered (few voxels, a voxel larger than the
    cloud, collinear points); raises :class:`RegistrationError` starting with ``label``."""
    try:
        grid = voxelize(points, voxel_size)
    except ShapeError as exc:  # more voxels across than the keys hold
        reach = float(points.abs().max()) / voxel_size
        raise RegistrationError(
            f"{label}: points lie {reach:.3g} voxels of {voxel_size:g} from the origin of "
            "their cloud (at most 1048576): the voxel size is too small for this cloud, or "
            "the unit is wrong (--voxel-size, --scale)"
        ) from exc
    kept = grid.point_index.numel()
    if kept < MIN_POINTS:
        raise RegistrationError(
            f"{label}: only {kept} voxel(s) at voxel size {voxel_size:g} m "
            f"(need at least {MIN_POINTS}); is the voxel size or the unit right?"
        )
    extent = float((points.max(dim=0).values - points.min(dim=0).values).max())
    if voxel_size > extent:
        raise RegistrationError(
            f"{label}: the voxel size {voxel_size:g} m is larger than the cloud "
            f"({extent:.3g} m across), too few points are left; use a smaller voxel size"
        )
    _check_not_collinear(points[grid.point_index].to(torch.float64), voxel_size, label)
    return grid


def _check_not_collinear(points: torch.Tensor, voxel_size: float, label: str) -> None:
    """Refuse ``points (M, 3)`` whose RMS distance from their principal line is below
    :data:`COLLINEAR_SPREAD` voxel sizes."""
    centred = points - points.mean(dim=0)
    singular = torch.linalg.svdvals(centred)  # descending
    spread = float(singular[1:].square().sum().div(points.shape[0]).sqrt())
    if spread < COLLINEAR_SPREAD * voxel_size:
        raise RegistrationError(
            f"{label}: the points are collinear (all within {spread:.2g} m of one line): "
            "the rotation about that line cannot be determined"
        )


class ByocExtractor:
    """The frozen geometric encoder on a voxelised cloud.

    Args:
        encoder: a :class:`byoc_cli.models.encoder.GeometricEncoder`, or a function of no
            arguments that returns one, called when the first cloud is encoded (a pair that
            FPFH registers alone never pays for building it); moved to ``device`` and put in
            eval mode.
        voxel_size: in the units of the points (metres).
        device: where the encoder runs.
    """

    name = "byoc"

    def __init__(
        self,
        encoder: torch.nn.Module | Callable[[], torch.nn.Module],
        voxel_size: float,
        device: str = "cpu",
    ) -> None:
        self.voxel_size = float(voxel_size)
        self.device = torch.device(device)
        self._lock = threading.Lock()
        self._load = None if isinstance(encoder, torch.nn.Module) else encoder
        self._encoder = None if self._load is not None else encoder.to(device).eval()

    @property
    def encoder(self) -> torch.nn.Module:
        """The encoder, built on first use (once, whichever thread asks first)."""
        if self._encoder is None:
            with self._lock:
                if self._encoder is None:
                    self._encoder = self._load().to(self.device).eval()
        return self._encoder

    @property
    def loaded(self) -> bool:
        """Whether the encoder is built."""
        return self._encoder is not None

    def __call__(
        self, points: torch.Tensor, label: str = "cloud", voxel_size: float | None = None
    ) -> CloudFeatures:
        """Features of ``points (N, 3)`` at ``voxel_size`` (None: the extractor's own)."""
        from byoc_cli.models.encoder import encode_voxels

        grid = _voxelize_checked(points, voxel_size or self.voxel_size, label)
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

    def __call__(
        self, points: torch.Tensor, label: str = "cloud", voxel_size: float | None = None
    ) -> CloudFeatures:
        """Features of ``points (N, 3)`` at ``voxel_size`` (None: the extractor's own)."""
        from byoc_cli.errors import require_open3d

        o3d = require_open3d()
        voxel = voxel_size or self.voxel_size
        grid = _voxelize_checked(points, voxel, label)
        kept = points[grid.point_index].to(torch.float64)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kept.numpy()))
        pcd.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=FPFH_NORMAL_RADIUS * voxel, max_nn=FPFH_NORMAL_MAX_NN
            )
        )
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pcd,
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=FPFH_FEATURE_RADIUS * voxel, max_nn=FPFH_FEATURE_MAX_NN
            ),
        )
        feats = torch.from_numpy(np.ascontiguousarray(np.asarray(fpfh.data).T, dtype=np.float32))
        feats = torch.nn.functional.normalize(feats, dim=1)
        return CloudFeatures(kept, feats, grid.point_index, grid.coords)
