"""Point-cloud files: PLY, NPY, PCD, XYZ/PTS, LAS/LAZ, E57 in; binary PLY out.

Everything here works on numpy arrays: a cloud is ``points (N, 3)`` float64. PLY (through
plyfile) and NPY (through numpy) need nothing else; PCD and the XYZ family are read with
open3d, imported lazily through :func:`byoc_cli.errors.require_open3d`. Open3D's readers
return an empty or silently padded cloud on a missing, truncated or garbage file, so each
file is checked here first (header, size) and the result is checked after. LAS/LAZ
(:mod:`byoc_cli.io.las`, laspy) and E57 (:mod:`byoc_cli.io.e57`, pye57) keep their
georeferenced coordinates in float64; one scan of a multi-scan E57 file is named
``site.e57:2`` (:mod:`byoc_cli.io.cloudpath`).

Every problem with a file raises :class:`~byoc_cli.errors.InputError` naming the file and
the problem in a short phrase; points with NaN or Inf coordinates are dropped and counted in
:attr:`LoadedCloud.num_nonfinite_dropped` (the caller decides whether to warn).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO, NamedTuple

import numpy as np

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io.cloudpath import parse_cloud_path
from byoc_cli.io.inputs import check_point_count, open_input
from byoc_cli.io.pcd import read_pcd_points, read_xyz_points
from byoc_cli.io.ply import _CHUNK_ROWS, read_ply_general, read_ply_points, write_ply

__all__ = [
    "SUPPORTED_EXTENSIONS",
    "LoadedCloud",
    "check_units",
    "read_point_cloud",
    "write_ply",
]

#: File extension (lower case) -> format name understood by :func:`read_point_cloud`.
SUPPORTED_EXTENSIONS: dict[str, str] = {
    ".ply": "ply",
    ".pcd": "pcd",
    ".xyz": "xyz",
    ".xyzn": "xyzn",
    ".xyzrgb": "xyzrgb",
    ".pts": "pts",
    ".npy": "npy",
    ".las": "las",
    ".laz": "laz",
    ".e57": "e57",
}
_FORMATS = tuple(dict.fromkeys(SUPPORTED_EXTENSIONS.values()))


class LoadedCloud(NamedTuple):
    """A point cloud read from a file.

    Attributes:
        points: ``(N, 3)`` float64, finite, N >= 1, a fresh writable array.
        num_nonfinite_dropped: points dropped because a coordinate was NaN or Inf.
        path: the file it was read from.
    """

    points: np.ndarray
    num_nonfinite_dropped: int
    path: Path


# ---------------------------------------------------------------------------- helpers


def _open_input(path: str | os.PathLike[str], kind: str = "cloud") -> BinaryIO:
    """Open an input file for binary reading (:func:`~byoc_cli.io.inputs.open_input`: a
    regular file within the cap of ``kind``, never a FIFO or a device) that is not empty.

    Raises:
        InputError: "no such file", "is a directory", "permission denied", "is a FIFO, not a
            regular file", "is 9 GiB, larger than ...", "empty file (0 bytes)",
            "cannot read: <reason>".
    """
    f = open_input(path, kind)
    if os.fstat(f.fileno()).st_size == 0:
        f.close()
        raise InputError(path, "empty file (0 bytes)")
    return f


def _drop_nonfinite(points: np.ndarray, path: str | os.PathLike[str]) -> LoadedCloud:
    """Drop rows with NaN/Inf, count them; error when nothing is left or nothing was there."""
    n = points.shape[0]
    if n == 0:
        raise InputError(path, "empty point cloud (0 points)")
    points = np.require(points, np.float64, ["C_CONTIGUOUS", "WRITEABLE", "OWNDATA"])
    # Compact the finite rows to the front block by block (no second (N, 3) array), then
    # shrink the buffer in place: the peak stays at the cloud plus one block.
    kept = 0
    for start in range(0, n, _CHUNK_ROWS):
        block = points[start : start + _CHUNK_ROWS]
        # the whole block at once first: a per-row reduction over 3 columns is slow
        finite = None if np.isfinite(block).all() else np.isfinite(block).all(axis=1)
        k = block.shape[0] if finite is None else int(np.count_nonzero(finite))
        if k == block.shape[0]:
            if kept != start:
                points[kept : kept + k] = block  # numpy buffers overlapping copies
        elif k:
            points[kept : kept + k] = block[finite]
        kept += k
    if kept == 0:
        raise InputError(path, f"no finite points (all {n} points have NaN or Inf coordinates)")
    if kept < n:
        points.resize((kept, 3), refcheck=False)  # we hold the only reference
    return LoadedCloud(points, n - kept, Path(path))


def _format_of(path: Path, fmt: str | None) -> str:
    supported = ", ".join(SUPPORTED_EXTENSIONS)
    if fmt is not None:
        name = fmt.lower().lstrip(".")
        if name not in _FORMATS:
            raise InputError(path, f"unsupported format {fmt!r} (supported: {', '.join(_FORMATS)})")
        return name
    suffix = path.suffix.lower()
    if not suffix:
        raise InputError(path, f"no file extension to tell the format (supported: {supported})")
    if suffix not in SUPPORTED_EXTENSIONS:
        raise InputError(path, f"unsupported extension {suffix!r} (supported: {supported})")
    return SUPPORTED_EXTENSIONS[suffix]


# ---------------------------------------------------------------------------- NPY


def _read_npy(path: Path) -> np.ndarray:
    with _open_input(path) as f:
        try:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        except Exception as exc:  # numpy's header parser raises many kinds (TokenError too)
            raise InputError(path, "not an NPY file (bad header)") from exc
        available = os.fstat(f.fileno()).st_size - f.tell()
    if any(not isinstance(n, int) or n < 0 for n in shape):
        raise InputError(path, f"not an NPY file (bad shape {tuple(shape)} in the header)")
    if len(shape) != 2 or shape[1] != 3:
        raise InputError(path, f"NPY array has shape {tuple(shape)}, expected (N, 3)")
    if dtype.kind not in "fiu":
        raise InputError(path, f"NPY array has dtype {dtype}, expected float or int")
    if shape[0] == 0:
        raise InputError(path, "empty point cloud (0 points)")
    check_point_count(shape[0], path)
    if shape[0] * 3 * dtype.itemsize > available:
        raise InputError(
            path,
            f"truncated or corrupt NPY file (header says {shape[0]} points, the data holds fewer)",
        )
    try:  # checked above to be a regular file of the size the header says
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, EOFError, OSError, OverflowError) as exc:
        raise InputError(path, f"truncated or corrupt NPY file ({exc})") from exc
    return np.array(array, dtype=np.float64, order="C")


# ---------------------------------------------------------------------------- by format


def _read_ply(path: Path) -> np.ndarray:
    with _open_input(path) as f:
        points = read_ply_points(f, path)
    if points is not None:
        return points
    with _open_input(path, "cloud-general") as f:
        return read_ply_general(f, path)


def _read_pcd(path: Path) -> np.ndarray:
    with _open_input(path, "cloud-open3d") as f:
        return read_pcd_points(f, path)


def _read_xyz(path: Path, fmt: str) -> np.ndarray:
    with _open_input(path, "cloud-open3d") as f:
        return read_xyz_points(f, path, fmt)


# ---------------------------------------------------------------------------- public


def read_point_cloud(path: str | os.PathLike[str], fmt: str | None = None) -> LoadedCloud:
    """Read a point cloud file into ``(N, 3)`` float64, dropping NaN/Inf points.

    The format comes from the extension (``.ply``, ``.pcd``, ``.xyz``, ``.xyzn``,
    ``.xyzrgb``, ``.pts``, ``.npy``, ``.las``, ``.laz``, ``.e57``; case-insensitive) unless
    ``fmt`` names one. PLY: ASCII
    or binary (either byte order), any numeric x/y/z type; other vertex properties and other
    elements (faces: a mesh gives its vertices) are ignored; binary data is read in chunks,
    so peak memory is about the result plus a few tens of MB. NPY: exactly ``(N, 3)`` of a
    float or int dtype, never unpickled. PCD and XYZ/PTS need open3d (a ``.pts`` count line
    is optional and checked against the points found). LAS/LAZ need laspy (and lazrs):
    x, y, z with the header's scales and offsets applied, in float64. E57 needs pye57: one
    scan in the file's frame (its pose applied, invalid points left out); a file with several
    scans is read one scan at a time, ``site.e57:2`` (0-based), and refused without one.

    Args:
        path: the file, or ``file.e57:K`` for scan K of an E57 file.
        fmt: format name overriding the extension (``"ply"``, ``"pcd"``, ``"xyz"``,
            ``"xyzn"``, ``"xyzrgb"``, ``"pts"``, ``"npy"``, ``"las"``, ``"laz"``, ``"e57"``).

    Returns:
        :class:`LoadedCloud` with finite ``points (N, 3)`` float64 (N >= 1), the number of
        points dropped for NaN/Inf coordinates, and the path.

    Raises:
        InputError: the file is missing, unreadable, of an unsupported format, malformed,
            truncated, empty, or holds no finite point; the message names the file.
        DependencyError: PCD/XYZ/PTS without a working open3d.
    """
    path = Path(path)
    file, scan = parse_cloud_path(path)
    name = _format_of(file, fmt)
    if scan is not None and name != "e57":
        raise InputError(path, f"a scan index (:{scan}) is for E57 files only")
    if name in ("las", "laz"):
        from byoc_cli.io.las import read_las_points

        return _drop_nonfinite(read_las_points(file), path)
    if name == "e57":
        from byoc_cli.io.e57 import read_e57_points

        return _drop_nonfinite(read_e57_points(file, scan), path)
    if name == "ply":
        points = _read_ply(path)
    elif name == "npy":
        points = _read_npy(path)
    elif name == "pcd":
        points = _read_pcd(path)
    else:
        points = _read_xyz(path, name)
    return _drop_nonfinite(points, path)


def check_units(
    points: np.ndarray, path: str | os.PathLike[str], max_extent: float = 1000.0
) -> None:
    """Refuse a cloud whose size suggests millimetres rather than metres.

    The CLI calls this only when the user did not pass ``--scale``.

    Args:
        points: ``(N, 3)`` finite coordinates (N may be 0).
        path: the file they came from, for the message.
        max_extent: the largest plausible bounding-box side in metres.

    Raises:
        InputError: the largest side of the axis-aligned bounding box exceeds ``max_extent``.
        ShapeError: ``points`` is not ``(N, 3)``.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points must be (N, 3), got {points.shape}")
    if points.shape[0] == 0:
        return
    extent = float(np.max(points.max(axis=0) - points.min(axis=0)))
    if extent > max_extent:
        raise InputError(
            path,
            f"extent {extent:.1f} along the largest axis looks like millimetres; "
            "pass --scale 0.001 (or --scale 1 to keep the units)",
        )
