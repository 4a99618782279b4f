"""PLY files: x, y, z of the vertices in (ASCII or binary, any numeric type), binary PLY out
(with colours, normals and float scalar properties).

Used through :func:`byoc_cli.io.pointcloud.read_point_cloud`, which opens the file and
handles NaN/Inf rows; :func:`write_ply` is re-exported there.
"""

from __future__ import annotations

import io
import itertools
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import BinaryIO

import numpy as np
import plyfile

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io.atomic import atomic_write, write_errors
from byoc_cli.io.inputs import MAX_CLOUD_POINTS, check_point_count

__all__ = ["read_ply_general", "read_ply_points", "write_ply"]

# Rows handled per block when reading binary PLY vertices and dropping NaN/Inf rows: bounds
# the extra memory beyond the (N, 3) float64 result to a few tens of MB.
_CHUNK_ROWS = 1 << 20
#: Fewest bytes one property of one element takes in an ASCII PLY file ("0 ").
_ASCII_PROPERTY_BYTES = 2


def _ply_header(f: BinaryIO, path: Path) -> plyfile.PlyData:
    """Parse the header with plyfile; ``f`` is left at the start of the data."""
    try:
        # plyfile has no public header-only reader; _parse_header is what PlyData.read uses.
        return plyfile.PlyData._parse_header(f)
    except plyfile.PlyHeaderParseError as exc:
        if exc.line == 1:
            raise InputError(path, "not a PLY file (bad header)") from exc
        raise InputError(path, f"bad PLY header (line {exc.line}: {exc.message})") from exc
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(path, "not a PLY file (bad header)") from exc


def _is_list(prop: plyfile.PlyProperty) -> bool:
    return isinstance(prop, plyfile.PlyListProperty)


def read_ply_general(f: BinaryIO, path: Path) -> np.ndarray:
    """General but slow path (list properties before or inside the vertex element) on the
    PLY file open as ``f`` (at its start)."""
    try:
        data = plyfile.PlyData.read(f, mmap=False)
        vertex = data["vertex"].data
        return np.stack([vertex[k].astype(np.float64) for k in "xyz"], axis=1)
    except plyfile.PlyElementParseError as exc:
        if exc.message == "early end-of-file":
            raise InputError(path, f"truncated PLY file ({exc})") from exc
        raise InputError(path, f"malformed PLY data ({exc})") from exc
    except (plyfile.PlyParseError, ValueError) as exc:
        raise InputError(path, f"malformed PLY data ({exc})") from exc


def _read_ply_binary(
    f: BinaryIO, path: Path, vertex: plyfile.PlyElement, byte_order: str, skip: int
) -> np.ndarray:
    """Read x, y, z of ``vertex`` (no list properties) in chunks of structured records."""
    dtype = vertex.dtype(byte_order)
    count = vertex.count
    f.seek(skip, io.SEEK_CUR)
    available = os.fstat(f.fileno()).st_size - f.tell()
    if available < count * dtype.itemsize:
        found = max(available, 0) // dtype.itemsize
        raise InputError(
            path, f"truncated PLY file (header says {count} vertices, data holds {found})"
        )
    check_point_count(count, path)
    out = np.empty((count, 3), dtype=np.float64)
    chunk = min(count, _CHUNK_ROWS)
    buf = bytearray(chunk * dtype.itemsize)
    view = memoryview(buf)
    for start in range(0, count, chunk):
        n = min(chunk, count - start)
        nbytes = n * dtype.itemsize
        got = f.readinto(view[:nbytes])
        if got != nbytes:  # the file shrank while we read it
            raise InputError(path, "truncated PLY file (early end of file)")
        records = np.frombuffer(buf, dtype=dtype, count=n)
        for j, name in enumerate("xyz"):
            out[start : start + n, j] = records[name]
    return out


def _read_ply_ascii(
    f: BinaryIO, path: Path, vertex: plyfile.PlyElement, skip_lines: int
) -> np.ndarray:
    """Read x, y, z of ``vertex`` (no list properties) from ASCII rows with numpy."""
    # no more rows than the rest of the file can hold: a header claiming 1e12 vertices must
    # not make numpy reserve memory for them
    available = os.fstat(f.fileno()).st_size - f.tell()
    text = io.TextIOWrapper(f, encoding="latin-1", newline=None)
    for _ in itertools.islice(text, skip_lines):
        pass
    names = [p.name for p in vertex.properties]
    cols = tuple(names.index(k) for k in "xyz")
    rows = min(vertex.count, available // (_ASCII_PROPERTY_BYTES * len(names)) + 1)
    if rows > MAX_CLOUD_POINTS:  # the file may hold them: refuse before reading
        check_point_count(vertex.count, path)
    try:
        with warnings.catch_warnings():  # "input contained no data": reported below
            warnings.simplefilter("ignore", UserWarning)
            out = np.loadtxt(
                text, dtype=np.float64, comments=None, usecols=cols, max_rows=rows, ndmin=2
            )
    except ValueError as exc:
        raise InputError(path, f"malformed ASCII PLY vertex data ({exc})") from exc
    if out.shape[0] < vertex.count:
        raise InputError(
            path, f"truncated PLY file (header says {vertex.count} vertices, found {out.shape[0]})"
        )
    return out


def _min_element_bytes(element: plyfile.PlyElement, text: bool, byte_order: str) -> int:
    """The fewest bytes one record of ``element`` takes (an empty list counts its length)."""
    if text:
        return _ASCII_PROPERTY_BYTES * len(element.properties)
    total = 0
    for prop in element.properties:
        kind = prop.list_dtype(byte_order)[0] if _is_list(prop) else prop.dtype(byte_order)
        total += np.dtype(kind).itemsize
    return total


def _check_counts_fit(f: BinaryIO, path: Path, header: plyfile.PlyData) -> None:
    """Refuse a header whose element counts the rest of the file cannot hold (a header
    claiming 1e12 vertices would otherwise ask for terabytes before reading a byte)."""
    available = os.fstat(f.fileno()).st_size - f.tell()
    need = sum(
        el.count * _min_element_bytes(el, header.text, header.byte_order) for el in header.elements
    )
    if need > available + header.text:  # the last ASCII value needs no separator
        counts = ", ".join(f"{el.count} {el.name} records" for el in header.elements)
        raise InputError(
            path,
            f"truncated PLY file (header says {counts}: at least {need} bytes, "
            f"the data holds {max(available, 0)})",
        )


def read_ply_points(f: BinaryIO, path: Path) -> np.ndarray | None:
    """x, y, z of the vertices of the PLY file open as ``f`` (at its start).

    Returns None when only the general (plyfile) reader can read it: call
    :func:`read_ply_general` after closing ``f``.

    Raises:
        InputError: a bad header, no x/y/z, a count the file cannot hold, truncated data.
    """
    header = _ply_header(f, path)
    names = [el.name for el in header.elements]
    if "vertex" not in names:
        raise InputError(path, "PLY has no vertex element")
    index = names.index("vertex")
    vertex = header.elements[index]
    props = {p.name: p for p in vertex.properties}
    missing = [k for k in "xyz" if k not in props or _is_list(props[k])]
    if missing:
        raise InputError(
            path, f"vertex element lacks x, y, z properties (missing {', '.join(missing)})"
        )
    if vertex.count < 0 or any(el.count < 0 for el in header.elements):
        raise InputError(path, "bad PLY header (negative element count)")
    if vertex.count == 0:
        raise InputError(path, "empty point cloud (0 points)")
    before = header.elements[:index]
    simple = not any(_is_list(p) for p in vertex.properties)
    if header.text and simple:
        return _read_ply_ascii(f, path, vertex, sum(el.count for el in before))
    if not header.text and simple and not any(_is_list(p) for el in before for p in el.properties):
        skip = sum(el.count * el.dtype(header.byte_order).itemsize for el in before)
        return _read_ply_binary(f, path, vertex, header.byte_order, skip)
    _check_counts_fit(f, path, header)  # before plyfile allocates what the header claims
    check_point_count(vertex.count, path)
    return None


def _as_uint8_colors(colors: np.ndarray, n: int) -> np.ndarray:
    colors = np.asarray(colors)
    if colors.shape != (n, 3):
        raise ShapeError(f"colors must be ({n}, 3) like points, got {colors.shape}")
    if colors.dtype == np.uint8:
        return colors
    if colors.dtype.kind in "iu" and (
        colors.size == 0 or (colors.min() >= 0 and colors.max() <= 255)
    ):
        return colors.astype(np.uint8)
    raise ShapeError(f"colors must be uint8 (or integers in 0..255), got {colors.dtype}")


#: coordinates this far from the origin are written as ``double``: float32 keeps steps of
#: 1 mm there (in metres), coarser farther out (0.5 m at a UTM northing of 5e6)
FLOAT32_LIMIT = 1e4


def coordinate_dtype(points: np.ndarray) -> np.dtype:
    """``float64`` when any coordinate of ``points (N, 3)`` reaches :data:`FLOAT32_LIMIT`
    in magnitude (or is not finite), else ``float32``."""
    points = np.asarray(points)
    if points.size and not np.abs(points).max() < FLOAT32_LIMIT:
        return np.dtype(np.float64)
    return np.dtype(np.float32)


def _checked_scalars(
    scalars: Mapping[str, np.ndarray] | None, n: int, taken: set[str]
) -> dict[str, np.ndarray]:
    """``scalars`` as ``(n,)`` arrays, each name a new PLY property name."""
    checked: dict[str, np.ndarray] = {}
    for name, values in (scalars or {}).items():
        values = np.asarray(values)
        if name in taken or not name.isidentifier():
            raise ShapeError(f"scalar name {name!r} is taken or not a plain name")
        if values.shape != (n,) or values.dtype.kind not in "fiu":
            raise ShapeError(f"scalar {name!r} must be real ({n},) like points, got {values.shape}")
        checked[name] = values
    return checked


def write_ply(
    path: str | os.PathLike[str] | None,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    *,
    dtype: type[np.floating] | str | None = None,
    scalars: Mapping[str, np.ndarray] | None = None,
) -> bytes | None:
    """Write a binary little-endian PLY file atomically (``path`` None: return its bytes).

    Vertex properties: ``x y z`` (``float`` or ``double``), then ``nx ny nz`` (same type)
    when ``normals`` are given, then ``red green blue`` (``uchar``) when ``colors`` are, then
    one ``float`` property per entry of ``scalars`` (CloudCompare shows them as scalar fields).

    Args:
        path: the output file (replaced atomically; nothing is left on failure), or None
            for the file's bytes (standard output).
        points: ``(N, 3)`` coordinates (any real dtype; N may be 0).
        colors: optional ``(N, 3)`` uint8 (or integers in 0..255).
        normals: optional ``(N, 3)`` real.
        dtype: ``np.float32`` or ``np.float64`` for coordinates and normals; None:
            :func:`coordinate_dtype` of ``points`` (``double`` for georeferenced points).
        scalars: optional per-point values, name -> ``(N,)`` real (names other than the
            properties above).

    Raises:
        ShapeError: wrong shapes, or a dtype other than float32/float64, or bad colors, or a
            scalar of another length or a name already used.
        InputError: the file cannot be written (missing folder, permission denied).
    """
    coord = np.dtype(coordinate_dtype(points) if dtype is None else dtype)
    if coord not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ShapeError(f"dtype must be float32 or float64, got {coord}")
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype.kind not in "fiu":
        raise ShapeError(f"points must be real (N, 3), got {points.shape} {points.dtype}")
    n = points.shape[0]
    fields: list[tuple[str, str]] = [(k, coord.newbyteorder("<").str) for k in "xyz"]
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != (n, 3) or normals.dtype.kind not in "fiu":
            raise ShapeError(f"normals must be real ({n}, 3) like points, got {normals.shape}")
        fields += [(k, coord.newbyteorder("<").str) for k in ("nx", "ny", "nz")]
    if colors is not None:
        colors = _as_uint8_colors(colors, n)
        fields += [(k, "u1") for k in ("red", "green", "blue")]
    scalars = _checked_scalars(scalars, n, {name for name, _ in fields})
    fields += [(k, "<f4") for k in scalars]
    vertex = np.empty(n, dtype=fields)
    for j, k in enumerate("xyz"):
        vertex[k] = points[:, j]
    if normals is not None:
        for j, k in enumerate(("nx", "ny", "nz")):
            vertex[k] = normals[:, j]
    if colors is not None:
        for j, k in enumerate(("red", "green", "blue")):
            vertex[k] = colors[:, j]
    for k, values in scalars.items():
        vertex[k] = values
    element = plyfile.PlyElement.describe(vertex, "vertex")
    ply = plyfile.PlyData([element], text=False, byte_order="<")
    if path is None:
        buffer = io.BytesIO()
        ply.write(buffer)
        return buffer.getvalue()
    with atomic_write(path, "wb") as f, write_errors(path):
        ply.write(f)
    return None
