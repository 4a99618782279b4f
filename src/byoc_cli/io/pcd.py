"""The formats open3d reads: PCD and the XYZ family (XYZ, XYZN, XYZRGB, PTS).

open3d is imported lazily through :func:`byoc_cli.errors.require_open3d`. Its readers
return an empty or silently padded cloud on a truncated or garbage file, so the header and
size are checked here first and the number of points read is checked after.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import BinaryIO

import numpy as np

from byoc_cli.errors import InputError, require_open3d

__all__ = ["read_pcd_points", "read_xyz_points"]


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


def read_pcd_points(f: BinaryIO, path: Path) -> np.ndarray:
    """x, y, z of the PCD file open as ``f``: the header and the size are checked here,
    then open3d reads it (it returns a padded or empty cloud on a bad file)."""
    header, offset = _pcd_header(f, path)
    size = os.fstat(f.fileno()).st_size
    fields = header.get("FIELDS", [])
    if not all(k in fields for k in "xyz"):
        raise InputError(path, f"PCD lacks x, y, z fields (has {', '.join(fields) or 'none'})")
    try:
        if "POINTS" in header:
            count = int(header["POINTS"][0])
        else:
            count = int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0])
        sizes = [int(v) for v in header.get("SIZE", [])]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(fields))]
        data = header["DATA"][0]
    except (KeyError, IndexError, ValueError) as exc:
        raise InputError(path, "not a PCD file (bad header)") from exc
    if count == 0:
        raise InputError(path, "empty point cloud (0 points)")
    if data == "ascii":
        lines = _count_lines(f)
        if lines < count:
            raise InputError(
                path, f"truncated PCD file (header says {count} points, found {lines} lines)"
            )
    elif data == "binary" and len(sizes) == len(counts) == len(fields):
        need = count * sum(s * c for s, c in zip(sizes, counts, strict=True))
        if size - offset < need:
            raise InputError(
                path, f"truncated PCD file (header says {count} points, data too short)"
            )
    elif data not in ("binary", "binary_compressed"):
        raise InputError(path, f"unsupported PCD data encoding {data!r}")
    points = _o3d_read(path, "pcd")
    if points.shape[0] != count:
        raise InputError(
            path,
            f"could not read PCD data (header says {count} points, open3d read "
            f"{points.shape[0]}; truncated or corrupt file?)",
        )
    return points


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
