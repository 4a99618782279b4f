"""Point-cloud files: PLY, NPY, PCD, XYZ/PTS in; binary PLY out.

Everything here works on numpy arrays: a cloud is ``points (N, 3)`` float64. PLY (through
plyfile) and NPY (through numpy) need nothing else; PCD and the XYZ family are read with
open3d, imported lazily through :func:`byoc_cli.errors.require_open3d`. Open3D's readers
return an empty or silently padded cloud on a missing, truncated or garbage file, so each
file is checked here first (header, size) and the result is checked after.

Every problem with a file raises :class:`~byoc_cli.errors.InputError` naming the file and
the problem in a short phrase; points with NaN or Inf coordinates are dropped and counted in
:attr:`LoadedCloud.num_nonfinite_dropped` (the caller decides whether to warn).
"""

from __future__ import annotations

import io
import itertools
import os
import re
import stat
from pathlib import Path
from typing import BinaryIO, NamedTuple

import numpy as np
import plyfile

from byoc_cli.errors import InputError, ShapeError, require_open3d
from byoc_cli.io.atomic import atomic_write, write_errors

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
}
_FORMATS = tuple(dict.fromkeys(SUPPORTED_EXTENSIONS.values()))

# Rows handled per block when reading binary PLY vertices and dropping NaN/Inf rows: bounds
# the extra memory beyond the (N, 3) float64 result to a few tens of MB.
_CHUNK_ROWS = 1 << 20


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


def _open_input(path: str | os.PathLike[str]) -> BinaryIO:
    """Open an input file for binary reading, turning OS errors into :class:`InputError`.

    Raises:
        InputError: "no such file", "is a directory", "permission denied",
            "empty file (0 bytes)", "cannot read: <reason>".
    """
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError) as exc:
        raise InputError(path, "no such file") from exc
    except PermissionError as exc:
        raise InputError(path, "permission denied") from exc
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from exc
    if stat.S_ISDIR(st.st_mode):
        raise InputError(path, "is a directory")
    try:
        f = open(path, "rb")
    except (FileNotFoundError, NotADirectoryError) as exc:
        raise InputError(path, "no such file") from exc
    except IsADirectoryError as exc:
        raise InputError(path, "is a directory") from exc
    except PermissionError as exc:
        raise InputError(path, "permission denied") from exc
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from exc
    if stat.S_ISREG(st.st_mode) and st.st_size == 0:
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
        finite = np.isfinite(block).all(axis=1)
        k = int(np.count_nonzero(finite))
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


# ---------------------------------------------------------------------------- PLY


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


def _read_ply_plyfile(path: Path) -> np.ndarray:
    """General but slow path (list properties before or inside the vertex element)."""
    try:
        data = plyfile.PlyData.read(str(path), mmap=False)
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
    text = io.TextIOWrapper(f, encoding="latin-1", newline=None)
    for _ in itertools.islice(text, skip_lines):
        pass
    names = [p.name for p in vertex.properties]
    cols = tuple(names.index(k) for k in "xyz")
    try:
        out = np.loadtxt(
            text, dtype=np.float64, comments=None, usecols=cols, max_rows=vertex.count, ndmin=2
        )
    except ValueError as exc:
        raise InputError(path, f"malformed ASCII PLY vertex data ({exc})") from exc
    if out.shape[0] < vertex.count:
        raise InputError(
            path, f"truncated PLY file (header says {vertex.count} vertices, found {out.shape[0]})"
        )
    return out


def _read_ply(path: Path) -> np.ndarray:
    with _open_input(path) as f:
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
        if (
            not header.text
            and simple
            and not any(_is_list(p) for el in before for p in el.properties)
        ):
            skip = sum(el.count * el.dtype(header.byte_order).itemsize for el in before)
            return _read_ply_binary(f, path, vertex, header.byte_order, skip)
    return _read_ply_plyfile(path)


# ---------------------------------------------------------------------------- NPY


def _read_npy(path: Path) -> np.ndarray:
    with _open_input(path) as f:
        try:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        except (ValueError, EOFError, OSError, SyntaxError) as exc:
            raise InputError(path, "not an NPY file (bad header)") from exc
    if len(shape) != 2 or shape[1] != 3:
        raise InputError(path, f"NPY array has shape {tuple(shape)}, expected (N, 3)")
    if dtype.kind not in "fiu":
        raise InputError(path, f"NPY array has dtype {dtype}, expected float or int")
    if shape[0] == 0:
        raise InputError(path, "empty point cloud (0 points)")
    try:
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise InputError(path, f"truncated or corrupt NPY file ({exc})") from exc
    return np.array(array, dtype=np.float64, order="C")


# ---------------------------------------------------------------------------- open3d formats


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


def _read_pcd(path: Path) -> np.ndarray:
    with _open_input(path) as f:
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


def _read_xyz(path: Path, fmt: str) -> np.ndarray:
    header_count = None
    with _open_input(path) as f:
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


# ---------------------------------------------------------------------------- public


def read_point_cloud(path: str | os.PathLike[str], fmt: str | None = None) -> LoadedCloud:
    """Read a point cloud file into ``(N, 3)`` float64, dropping NaN/Inf points.

    The format comes from the extension (``.ply``, ``.pcd``, ``.xyz``, ``.xyzn``,
    ``.xyzrgb``, ``.pts``, ``.npy``; case-insensitive) unless ``fmt`` names one. PLY: ASCII
    or binary (either byte order), any numeric x/y/z type; other vertex properties and other
    elements (faces: a mesh gives its vertices) are ignored; binary data is read in chunks,
    so peak memory is about the result plus a few tens of MB. NPY: exactly ``(N, 3)`` of a
    float or int dtype, never unpickled. PCD and XYZ/PTS need open3d (a ``.pts`` count line
    is optional and checked against the points found).

    Args:
        path: the file.
        fmt: format name overriding the extension (``"ply"``, ``"pcd"``, ``"xyz"``,
            ``"xyzn"``, ``"xyzrgb"``, ``"pts"``, ``"npy"``).

    Returns:
        :class:`LoadedCloud` with finite ``points (N, 3)`` float64 (N >= 1), the number of
        points dropped for NaN/Inf coordinates, and the path.

    Raises:
        InputError: the file is missing, unreadable, of an unsupported format, malformed,
            truncated, empty, or holds no finite point; the message names the file.
        DependencyError: PCD/XYZ/PTS without a working open3d.
    """
    path = Path(path)
    name = _format_of(path, fmt)
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


def write_ply(
    path: str | os.PathLike[str],
    points: np.ndarray,
    colors: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    *,
    dtype: type[np.floating] | str = np.float32,
) -> None:
    """Write a binary little-endian PLY file atomically.

    Vertex properties: ``x y z`` (``float`` or ``double``), then ``nx ny nz`` (same type)
    when ``normals`` are given, then ``red green blue`` (``uchar``) when ``colors`` are.

    Args:
        path: the output file (replaced atomically; nothing is left on failure).
        points: ``(N, 3)`` coordinates (any real dtype; N may be 0).
        colors: optional ``(N, 3)`` uint8 (or integers in 0..255).
        normals: optional ``(N, 3)`` real.
        dtype: ``np.float32`` (default) or ``np.float64`` for coordinates and normals.

    Raises:
        ShapeError: wrong shapes, or a dtype other than float32/float64, or bad colors.
        InputError: the file cannot be written (missing folder, permission denied).
    """
    coord = np.dtype(dtype)
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
    vertex = np.empty(n, dtype=fields)
    for j, k in enumerate("xyz"):
        vertex[k] = points[:, j]
    if normals is not None:
        for j, k in enumerate(("nx", "ny", "nz")):
            vertex[k] = normals[:, j]
    if colors is not None:
        for j, k in enumerate(("red", "green", "blue")):
            vertex[k] = colors[:, j]
    element = plyfile.PlyElement.describe(vertex, "vertex")
    ply = plyfile.PlyData([element], text=False, byte_order="<")
    with atomic_write(path, "wb") as f, write_errors(path):
        ply.write(f)
