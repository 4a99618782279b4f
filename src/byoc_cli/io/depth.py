"""Depth images and pinhole intrinsics: read them and back-project depth to 3-D points.

Camera axes are OpenCV's: x right, y down, z forward (the optical axis); a pixel ``(u, v)``
is column ``u``, row ``v`` and, by default, is back-projected through its centre
``(u + 0.5, v + 0.5)``.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io.matrix import _parse_rows, _read_text, _shape_phrase
from byoc_cli.io.pointcloud import LoadedCloud, _open_input

__all__ = [
    "Intrinsics",
    "depth_to_points",
    "read_depth_cloud",
    "read_depth_image",
    "read_intrinsics",
]

#: Raw value that marks a missing measurement in 16-bit depth images (raw 7-Scenes).
INVALID_DEPTH_16 = 65535
#: Plausible focal lengths in pixels (a depth camera has a few hundred to a few thousand);
#: outside, a file is refused instead of back-projecting to absurd coordinates.
FOCAL_RANGE_PX = (1.0, 1e6)
#: Largest principal-point coordinate or skew in pixels, and largest image side.
MAX_PIXEL_COORD = 1e6
MAX_IMAGE_SIDE = 100_000
#: Largest depth image read (pixels): a header claiming more is refused before decoding.
MAX_DEPTH_PIXELS = 64_000_000


class Intrinsics(NamedTuple):
    """Pinhole intrinsics.

    Attributes:
        K: ``(3, 3)`` float64 ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.
        width: image width in pixels, or None when the file does not say.
        height: image height in pixels, or None when the file does not say.
    """

    K: np.ndarray
    width: int | None
    height: int | None


def _fmt(values: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:g}" for v in np.ravel(values)) + "]"


def _validate_K(K: np.ndarray, path: Path) -> np.ndarray:
    if not np.all(np.isfinite(K)):
        raise InputError(path, "intrinsic matrix has NaN or Inf entries")
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9) or abs(K[1, 0]) > 1e-9:
        raise InputError(
            path,
            f"intrinsic matrix rows are {_fmt(K[0])}, {_fmt(K[1])}, {_fmt(K[2])}; expected "
            "[fx, s, cx], [0, fy, cy], [0, 0, 1] (transposed?)",
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"focal lengths must be positive (fx={K[0, 0]:g}, fy={K[1, 1]:g})")
    low, high = FOCAL_RANGE_PX
    if not (low <= K[0, 0] <= high and low <= K[1, 1] <= high):
        raise InputError(
            path,
            f"focal lengths fx={K[0, 0]:g}, fy={K[1, 1]:g} are not plausible "
            f"(expected {low:g} to {high:g} pixels)",
        )
    if np.abs(K[:2, 1:]).max() > MAX_PIXEL_COORD:
        raise InputError(
            path, f"principal point or skew beyond {MAX_PIXEL_COORD:g} pixels: {_fmt(K[:2])}"
        )
    return K


def _image_size(value: object, key: str, path: Path) -> int | None:
    if value is None:
        return None
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if not number or not math.isfinite(value) or value != int(value) or value <= 0:
        raise InputError(path, f"'{key}' must be a positive integer, got {value!r}")
    if value > MAX_IMAGE_SIDE:
        raise InputError(path, f"'{key}' is {value:g}, more than {MAX_IMAGE_SIDE} pixels")
    return int(value)


def _intrinsics_from_json(text: str, path: Path) -> Intrinsics:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON (line {exc.lineno}: {exc.msg})") from exc
    except RecursionError as exc:
        raise InputError(path, "not valid JSON (nested too deeply)") from exc
    if isinstance(data, dict) and "intrinsic_matrix" not in data and "intrinsic" in data:
        data = data["intrinsic"]  # Open3D PinholeCameraParameters
    if not isinstance(data, dict) or "intrinsic_matrix" not in data:
        raise InputError(
            path, "JSON lacks 'intrinsic_matrix' (expected Open3D PinholeCameraIntrinsic)"
        )
    values = data["intrinsic_matrix"]
    if not isinstance(values, list) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in values
    ):
        raise InputError(path, "'intrinsic_matrix' must be a flat list of 9 numbers")
    if len(values) != 9:
        raise InputError(path, f"'intrinsic_matrix' has {len(values)} numbers, expected 9")
    K = np.array(values, dtype=np.float64).reshape(3, 3, order="F")  # column-major
    return Intrinsics(
        _validate_K(K, path),
        _image_size(data.get("width"), "width", path),
        _image_size(data.get("height"), "height", path),
    )


def _intrinsics_from_text(text: str, path: Path) -> Intrinsics:
    rows = _parse_rows(text, path)
    widths = sorted({len(r) for r in rows})
    if len(rows) == 4 and widths == [4]:  # ScanNet's intrinsic_depth.txt: K padded to 4x4
        M = np.array(rows, dtype=np.float64)
        if np.allclose(M[3], [0, 0, 0, 1]) and np.allclose(M[:3, 3], 0):
            return Intrinsics(_validate_K(M[:3, :3].copy(), path), None, None)
    if len(rows) != 3 or widths != [3]:
        raise InputError(path, f"expected a 3x3 matrix, found {_shape_phrase(rows)}")
    return Intrinsics(_validate_K(np.array(rows, dtype=np.float64), path), None, None)


def read_intrinsics(path: str | os.PathLike[str]) -> Intrinsics:
    """Read pinhole intrinsics from Open3D JSON or a 3x3 text matrix.

    Formats: Open3D ``PinholeCameraIntrinsic`` JSON (``{"width", "height",
    "intrinsic_matrix": [9 numbers, column-major]}``; also inside a
    ``PinholeCameraParameters`` file's ``"intrinsic"``), or text with the 3x3 matrix as 3
    rows of 3 numbers (3DMatch ``camera-intrinsics.txt``; ScanNet's 4x4 ``intrinsic_depth.txt``
    is accepted too).

    Args:
        path: the file.

    Returns:
        :class:`Intrinsics` (``K (3, 3)`` float64; width and height from JSON, else None).

    Raises:
        InputError: missing/unreadable file, bad JSON or text, wrong shape, a last row other
            than ``[0, 0, 1]``, non-positive focal lengths; the message names the file.
    """
    path = Path(path)
    text = _read_text(path, "intrinsics")
    if path.suffix.lower() == ".json" or text.lstrip().startswith("{"):
        return _intrinsics_from_json(text, path)
    return _intrinsics_from_text(text, path)


def valid_depth(depth_m: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Check a depth image and its intrinsics; returns ``(depth_m, K, valid (H, W) bool)``.

    Raises:
        ShapeError: ``depth_m`` is not 2-D or ``K`` is not 3x3.
        ValueError: ``K`` is not finite and invertible.
    """
    depth_m = np.asarray(depth_m)
    K = np.asarray(K, dtype=np.float64)
    if depth_m.ndim != 2:
        raise ShapeError(f"depth_m must be (H, W), got {depth_m.shape}")
    if K.shape != (3, 3):
        raise ShapeError(f"K must be (3, 3), got {K.shape}")
    if not np.all(np.isfinite(K)) or abs(np.linalg.det(K)) < 1e-12:
        raise ValueError("K must be a finite invertible matrix")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth_m) & (depth_m > 0)
    return depth_m, K, valid


def depth_to_points(depth_m: np.ndarray, K: np.ndarray, *, pixel_offset: float = 0.5) -> np.ndarray:
    """Back-project a depth image to camera-frame points.

    Pixel ``(u, v)`` (column, row) with depth ``z`` gives
    ``z * K^-1 [u + pixel_offset, v + pixel_offset, 1]`` in OpenCV axes (x right, y down,
    z forward). Pixels with depth ``<= 0`` or non-finite are skipped. Points come in row-major
    pixel order.

    Args:
        depth_m: ``(H, W)`` depth along the optical axis in metres (any real dtype).
        K: ``(3, 3)`` intrinsic matrix.
        pixel_offset: where in a pixel the ray goes through: 0.5 (default) is its centre
            when integer coordinates are pixel corners; 0.0 matches Open3D's
            ``create_from_depth_image`` (integer coordinates at pixel centres).

    Returns:
        ``(N, 3)`` float64 points, N = number of valid pixels (may be 0).

    Raises:
        ShapeError: ``depth_m`` is not 2-D or ``K`` is not 3x3.
        ValueError: ``K`` is not finite and invertible.
    """
    depth_m, K, valid = valid_depth(depth_m, K)
    v, u = np.nonzero(valid)
    z = depth_m[valid].astype(np.float64)
    pixels = np.stack(
        [u.astype(np.float64) + pixel_offset, v.astype(np.float64) + pixel_offset, np.ones_like(z)],
        axis=1,
    )
    rays = pixels @ np.linalg.inv(K).T
    return rays * z[:, None]


def _check_depth_scale(depth_scale: float) -> float:
    depth_scale = float(depth_scale)
    if not np.isfinite(depth_scale) or depth_scale <= 0:
        raise ValueError(f"depth_scale must be positive (raw units per metre), got {depth_scale}")
    return depth_scale


def read_depth_image(path: str | os.PathLike[str], depth_scale: float) -> np.ndarray:
    """Read a depth image as metres.

    16-bit grayscale PNG (or TIFF) with raw values ``depth_scale`` per metre, 0 and 65535
    marking missing depth; 32-bit integer and float images are read the same way (NaN/Inf
    kept as they are in float images).

    Args:
        path: the image.
        depth_scale: raw units per metre, e.g. 1000 for millimetres, 5000 for TUM RGB-D,
            1 for float images in metres.

    Returns:
        ``(H, W)`` float32 depth in metres; missing depth is 0.

    Raises:
        InputError: missing/unreadable file, not an image, truncated image, or a pixel
            format that is not a depth map (8-bit, colour); the message names the file.
        ValueError: ``depth_scale`` is not a positive number.
    """
    from PIL import Image, UnidentifiedImageError

    depth_scale = _check_depth_scale(depth_scale)
    path = Path(path)
    with _open_input(path, "image") as f:
        try:
            with Image.open(f) as image:
                mode = image.mode
                if mode not in ("I;16", "I;16L", "I;16B", "I;16N", "I", "F"):
                    raise InputError(
                        path,
                        f"not a depth image (pixel format {mode!r}; expected 16-bit grayscale "
                        "PNG/TIFF or a 32-bit float TIFF)",
                    )
                if image.width * image.height > MAX_DEPTH_PIXELS:
                    raise InputError(
                        path,
                        f"image of {image.width} x {image.height} pixels is larger than a "
                        f"depth image can be ({MAX_DEPTH_PIXELS:,} pixels at most)",
                    )
                raw = np.asarray(image)
        except Image.DecompressionBombError as exc:
            raise InputError(path, f"image too large to read ({exc})") from exc
        except UnidentifiedImageError as exc:
            raise InputError(path, "not an image file (pillow cannot identify it)") from exc
        except (OSError, SyntaxError, ValueError) as exc:
            raise InputError(path, f"truncated or corrupt image ({exc})") from exc
    if raw.ndim != 2:
        raise InputError(path, f"not a depth image (array of shape {raw.shape})")
    if raw.dtype.kind == "f":
        return (raw.astype(np.float32) / np.float32(depth_scale)).astype(np.float32)
    invalid = (raw <= 0) | (raw == INVALID_DEPTH_16)
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[invalid] = 0.0
    return depth


def read_depth_cloud(
    depth_path: str | os.PathLike[str],
    intrinsics_path: str | os.PathLike[str],
    depth_scale: float = 1000.0,
    depth_trunc: float | None = None,
) -> LoadedCloud:
    """Read a depth image and back-project it to a camera-frame cloud.

    Args:
        depth_path: the depth image (see :func:`read_depth_image`).
        intrinsics_path: the intrinsics (see :func:`read_intrinsics`); when it states the
            image size, the depth image must match it.
        depth_scale: raw units per metre (1000 = millimetres, 5000 = TUM).
        depth_trunc: when given, depths beyond it (metres) are dropped too.

    Returns:
        :class:`LoadedCloud` with ``points (N, 3)`` float64 in metres (OpenCV camera axes,
        pixel centres), ``num_nonfinite_dropped`` = NaN/Inf pixels of a float image, and
        ``path = depth_path``.

    Raises:
        InputError: a file cannot be used (naming it), the sizes disagree, or no pixel has
            valid depth.
        ValueError: ``depth_scale`` or ``depth_trunc`` is not a positive number.
    """
    depth_path = Path(depth_path)
    if depth_trunc is not None and not (np.isfinite(depth_trunc) and depth_trunc > 0):
        raise ValueError(f"depth_trunc must be positive metres, got {depth_trunc}")
    intrinsics = read_intrinsics(intrinsics_path)
    depth = read_depth_image(depth_path, depth_scale)
    height, width = depth.shape
    if (intrinsics.width is not None and intrinsics.width != width) or (
        intrinsics.height is not None and intrinsics.height != height
    ):
        raise InputError(
            intrinsics_path,
            f"intrinsics are for {intrinsics.width}x{intrinsics.height} images but "
            f"{depth_path.name} is {width}x{height}",
        )
    nonfinite = int(np.count_nonzero(~np.isfinite(depth)))
    if depth_trunc is not None:
        with np.errstate(invalid="ignore"):
            depth = np.where(depth > depth_trunc, np.float32(0.0), depth)
    points = depth_to_points(depth, intrinsics.K)
    if points.shape[0] == 0:
        within = f" within depth_trunc {depth_trunc:g} m" if depth_trunc is not None else ""
        raise InputError(depth_path, f"no valid depth pixels{within} (all 0 or invalid)")
    return LoadedCloud(points, nonfinite, depth_path)
