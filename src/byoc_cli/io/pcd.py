"""The formats open3d reads: PCD and the XYZ family (XYZ, XYZN, XYZRGB, PTS).

open3d is imported lazily through :func:`byoc_cli.errors.require_open3d`. Its readers
return an empty or silently padded cloud on a truncated or garbage file, so the header and
size are checked here first and the number of points read is checked after.
"""

from __future__ import annotations

import os
import re
import struct
from pathlib import Path
from typing import BinaryIO

import numpy as np

from byoc_cli.errors import InputError, require_open3d
from byoc_cli.io.inputs import MAX_OPEN3D_POINTS, check_point_count

__all__ = ["read_pcd_points", "read_xyz_points"]

#: Largest COUNT (values per field) accepted in a PCD header (FPFH histograms have 33).
_MAX_PCD_COUNT = 1024


def _o3d_read(path: Path, fmt: str) -> np.ndarray:
    o3d = require_open3d()
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            cloud = o3d.io.read_point_cloud(
                str(path), format=fmt, remove_nan_points=False, remove_infinite_points=False
            )
    except RuntimeError as exc:
        raise InputError(path, f"open3d cannot read it ({exc})") from exc
    return np.array(cloud.points, dtype=np.float64)


_PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS")


def _pcd_header(f: BinaryIO, path: Path) -> tuple[dict[str, list[str]], int]:
    """Parse a PCD header (up to and including ``DATA``); returns ``(fields, data_offset)``."""
    header: dict[str, list[str]] = {}
    for _ in range(64):
        raw = f.readline(4096)
        if not raw:
            break
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            break
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        key = key.upper()
        if key == "DATA":
            header["DATA"] = [v.lower() for v in values]
            return header, f.tell()
        if key not in _PCD_KEYS:
            break
        header[key] = values
    raise InputError(path, "not a PCD file (bad header)")


def _pcd_layout(header: dict[str, list[str]], path: Path) -> tuple[int, int, str]:
    """Check the header's numbers against the PCD spec before open3d trusts them.

    Returns:
        ``(points, bytes per point, data encoding)``.
    """
    fields = header.get("FIELDS", [])
    if not all(k in fields for k in "xyz"):
        raise InputError(path, f"PCD lacks x, y, z fields (has {', '.join(fields) or 'none'})")
    try:
        width = int(header["WIDTH"][0])
        height = int(header.get("HEIGHT", ["1"])[0])
        count = int(header["POINTS"][0]) if "POINTS" in header else width * height
        sizes = [int(v) for v in header["SIZE"]]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(fields))]
        types = header["TYPE"]
        data = header["DATA"][0]
    except (KeyError, IndexError, ValueError) as exc:
        raise InputError(path, "not a PCD file (bad header)") from exc
    if not len(sizes) == len(counts) == len(types) == len(fields):
        raise InputError(path, "bad PCD header (FIELDS, SIZE, TYPE and COUNT differ in length)")
    if any(s not in (1, 2, 4, 8) for s in sizes) or any(t not in ("F", "I", "U") for t in types):
        raise InputError(path, "bad PCD header (SIZE must be 1, 2, 4 or 8 and TYPE F, I or U)")
    if any(not 1 <= c <= _MAX_PCD_COUNT for c in counts) or min(width, height, count) < 0:
        raise InputError(path, "bad PCD header (a COUNT, WIDTH, HEIGHT or POINTS out of range)")
    if count != width * height:
        raise InputError(path, f"bad PCD header (POINTS {count} is not WIDTH x HEIGHT)")
    return count, sum(s * c for s, c in zip(sizes, counts, strict=True)), data


def read_pcd_points(f: BinaryIO, path: Path) -> np.ndarray:
    """x, y, z of the PCD file open as ``f``: the header and the size are checked here,
    then open3d reads it (it returns a padded or empty cloud on a bad file, and crashes on
    some headers that lie)."""
    header, offset = _pcd_header(f, path)
    available = os.fstat(f.fileno()).st_size - offset
    count, row_bytes, data = _pcd_layout(header, path)
    if count == 0:
        raise InputError(path, "empty point cloud (0 points)")
    check_point_count(count, path, MAX_OPEN3D_POINTS)
    if data == "ascii":
        lines = _count_lines(f)
        if lines < count:
            raise InputError(
                path, f"truncated PCD file (header says {count} points, found {lines} lines)"
            )
    elif data == "binary":
        if available < count * row_bytes:
            raise InputError(
                path, f"truncated PCD file (header says {count} points, data too short)"
            )
    elif data == "binary_compressed":
        _check_compressed(f, path, count * row_bytes, available)
    else:
        raise InputError(path, f"unsupported PCD data encoding {data!r}")
    points = _o3d_read(path, "pcd")
    if points.shape[0] != count:
        raise InputError(
            path,
            f"could not read PCD data (header says {count} points, open3d read "
            f"{points.shape[0]}; truncated or corrupt file?)",
        )
    return points


def _check_compressed(f: BinaryIO, path: Path, expected: int, available: int) -> None:
    """binary_compressed: two uint32 sizes, then the LZF data; both sizes must agree."""
    sizes = f.read(8)
    if len(sizes) < 8:
        raise InputError(path, "could not read PCD data (no compressed data)")
    compressed, uncompressed = struct.unpack("<II", sizes)
    if uncompressed != expected or compressed > available - 8 or compressed == 0:
        raise InputError(
            path,
            f"could not read PCD data (compressed sizes {compressed} / {uncompressed} bytes, "
            f"expected {expected} uncompressed within {available - 8}; truncated or corrupt "
            "file?)",
        )


def _count_lines(f: BinaryIO) -> int:
    """Lines from the current position to the end (a last line without newline counts)."""
    lines = 0
    last = b"\n"
    while chunk := f.read(1 << 24):
        lines += chunk.count(b"\n")
        last = chunk[-1:]
    return lines + (last != b"\n")


_PTS_COUNT = re.compile(rb"^\s*(\d+)\s*$")


def read_xyz_points(f: BinaryIO, path: Path, fmt: str) -> np.ndarray:
    """x, y, z of an XYZ-family file (``xyz``, ``xyzn``, ``xyzrgb``, ``pts``) open as ``f``
    (only its first line is read here; open3d reads the file)."""
    header_count = None
    if fmt == "pts":
        first = f.readline(256)
        match = _PTS_COUNT.match(first)
        if match:
            header_count = int(match.group(1))
    if fmt == "pts":
        # Open3D's own PTS reader trusts the count line blindly (pads with zeros when the file
        # is shorter, takes the first number of the first point as the count when there is no
        # count line), so .pts files are read as XYZ (the count line does not parse as a
        # point and is skipped) and the count is checked here.
        fmt = "xyz"
        if header_count == 0:
            raise InputError(path, "empty point cloud (0 points)")
    points = _o3d_read(path, fmt)
    if points.shape[0] == 0:
        expected = {"xyz": "x y z", "xyzn": "x y z nx ny nz", "xyzrgb": "x y z r g b"}[fmt]
        raise InputError(path, f"no points found (expected lines of '{expected}')")
    if header_count is not None and points.shape[0] != header_count:
        raise InputError(
            path, f"PTS header says {header_count} points, the file holds {points.shape[0]}"
        )
    return points
