"""How the register engine reads its inputs: clouds (files or arrays) in metres, depth images
at their depth scale, and weights files."""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from byoc_cli.pipeline.weights import LoadedWeights

#: inputs read as depth images (they need intrinsics)
DEPTH_EXTENSIONS = (".png", ".tif", ".tiff")
#: the depth scale of a depth image outside any known layout (millimetres)
DEFAULT_DEPTH_SCALE = 1000.0
#: the median depth any depth sensor sees, in metres: outside it the depth scale is wrong
PLAUSIBLE_DEPTH = (0.1, 20.0)


def load_weights(path: str | os.PathLike[str] | None = None) -> LoadedWeights:
    """Load a weights file (weights-spec/ format); None loads the shipped default weights.

    Returns:
        a ``LoadedWeights`` (``encoder``, ``metadata``, ``file_sha256``, ``path``) that
        :func:`byoc_cli.api.register`, :func:`byoc_cli.api.extract_features` and
        :class:`~byoc_cli.pipeline.registrar.Registrar` take as ``weights``.

    Raises:
        WeightsError: the file is missing or invalid, or (None) nothing ships or the shipped
            file does not match its checksum.
    """
    if path is None:
        from byoc_cli.pipeline.default_weights import load_default_weights

        return load_default_weights()
    from byoc_cli.pipeline.weights import load_weights as _load

    return _load(path)


def depth_scale_of(path: str | os.PathLike[str], depth_scale: float | None = None):
    """The depth scale (raw units per metre) to read the depth image ``path`` with, and where
    it comes from: ``depth_scale`` when given (``"given"``), else the convention of the
    dataset layout around the file (``"tum layout of SEQ"``: TUM's ``depth.txt`` beside
    ``depth/`` is 5000; 3DMatch, ScanNet and Redwood are 1000), else
    :data:`DEFAULT_DEPTH_SCALE` (``"default"``).

    Returns:
        ``(depth_scale, source)``.
    """
    if depth_scale is not None:
        return float(depth_scale), "given"
    from byoc_cli.io.rgbd.registry import layout_of_depth_image

    found = layout_of_depth_image(Path(path))
    if found is None:
        return DEFAULT_DEPTH_SCALE, "default"
    layout, folder = found
    return float(layout.depth_scale), f"{layout.name} layout of {folder}"


def check_depth_range(points: np.ndarray, path: Any, depth_scale: float) -> None:
    """Refuse depth-image points whose median depth no depth sensor sees
    (:data:`PLAUSIBLE_DEPTH`): the depth scale is wrong.

    Raises:
        InputError: naming ``path``, the median depth and ``--depth-scale``.
    """
    from byoc_cli.errors import InputError

    if len(points) == 0:
        return
    median = float(np.median(points[:, 2]))
    low, high = PLAUSIBLE_DEPTH
    if not low <= median <= high:
        raise InputError(
            path,
            f"median depth {median:.3g} m at --depth-scale {depth_scale:g} (units per metre) "
            f"is outside what depth sensors see ({low:g}-{high:g} m): give this data's "
            "--depth-scale (1000 for millimetres, 5000 for TUM)",
        )


def load_cloud(
    path: str | os.PathLike[str],
    *,
    intrinsics: str | os.PathLike[str] | None = None,
    depth_scale: float | None = None,
    scale: float | None = None,
) -> np.ndarray:
    """Read a point cloud (.ply, .pcd, .xyz, .pts, .npy, .las, .laz, .e57) or a depth image as
    ``(N, 3)`` metres.

    Points with NaN/Inf coordinates are dropped (with a warning). LAS/LAZ and E57 keep their
    georeferenced coordinates in float64 (:func:`byoc_cli.io.read_point_cloud`).

    Args:
        path: the file, or ``file.e57:K`` for scan K (0-based) of a multi-scan E57 file.
        intrinsics: for depth images (.png, .tif): Open3D intrinsics JSON or a 3x3 text matrix.
        depth_scale: depth-image units per metre; None: the convention of the dataset layout
            around the file, else 1000 (:func:`depth_scale_of`).
        scale: multiply the coordinates by this (0.001 for millimetres); None checks that the
            cloud looks like metres.

    Returns:
        ``(N, 3)`` float64 (times ``scale`` when given).

    Raises:
        InputError: unreadable or malformed file, a depth image without intrinsics or whose
            median depth is outside 0.1-20 m (a wrong depth scale), or (no ``scale``) a cloud
            that looks like millimetres.
    """
    from byoc_cli.errors import InputError
    from byoc_cli.io import check_units, read_depth_cloud, read_point_cloud

    path = Path(path)
    if path.suffix.lower() in DEPTH_EXTENSIONS:
        if intrinsics is None:
            raise InputError(path, "is a depth image: intrinsics are required (--intrinsics)")
        depth_scale, _ = depth_scale_of(path, depth_scale)
        loaded = read_depth_cloud(path, Path(intrinsics), depth_scale=depth_scale)
        check_depth_range(loaded.points, path, depth_scale)
    else:
        loaded = read_point_cloud(path)
    if loaded.num_nonfinite_dropped:
        warnings.warn(
            f"{path}: dropped {loaded.num_nonfinite_dropped} point(s) with NaN/Inf coordinates",
            stacklevel=2,
        )
    points = loaded.points
    if scale is None:
        check_units(points, path)
        return points
    return points * scale


def as_points(cloud: Any, label: str, scale: float | None, **load: Any) -> tuple[np.ndarray, str]:
    """A path is read with :func:`load_cloud`; an array is checked and scaled the same way."""
    if isinstance(cloud, (str, os.PathLike)):
        return load_cloud(cloud, scale=scale, **load), str(cloud)
    from byoc_cli.errors import ShapeError
    from byoc_cli.io import check_units

    points = np.asarray(cloud, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ShapeError(f"{label}: points must be (N, 3) with N >= 1, got {points.shape}")
    if not np.isfinite(points).all():
        raise ShapeError(f"{label}: points must be finite")
    if scale is None:
        check_units(points, label)
        return points, label
    return points * scale, label
