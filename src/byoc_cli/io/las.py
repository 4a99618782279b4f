"""LAS and LAZ files (ASPRS lidar exchange format), read and written with laspy.

A LAS point stores its coordinates as int32 ``X, Y, Z`` with a scale and an offset per axis in
the header (``x = X * scale + offset``): georeferenced data (UTM eastings of 5e5, northings of
4e6 to 5e6 metres) keeps millimetres that way. The reader returns ``x, y, z`` with the header's
scales and offsets applied, in float64 (laspy's scaled dimensions), never through float32.
LAZ is the same format compressed; laspy reads and writes it through its ``lazrs`` backend.

laspy is imported lazily (``pip install 'laspy[lazrs]'``); a missing laspy or lazrs is an
:class:`~byoc_cli.errors.InputError` naming the file and the install command.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io.atomic import atomic_write, write_errors
from byoc_cli.io.inputs import check_point_count, open_input

__all__ = ["LAS_EXTENSIONS", "read_las_points", "write_las_like"]

#: file extensions (lower case) read and written here
LAS_EXTENSIONS = (".las", ".laz")
#: points decoded per block: bounds the memory beyond the ``(N, 3)`` float64 result
_CHUNK_POINTS = 1 << 20
#: the range of LAS's int32 coordinates
_INT32 = (np.iinfo(np.int32).min, np.iinfo(np.int32).max)
_INSTALL = "pip install 'laspy[lazrs]'"
#: the most points a LAZ chunk may hold (LASzip writes 50,000): lazrs allocates a chunk's
#: points at once, and a corrupt chunk size aborts the process on an allocation of many GB
MAX_CHUNK_POINTS = 5_000_000
_VARIABLE_CHUNKS = 0xFFFFFFFF


class _DropLogRecords(logging.Filter):
    """laspy and lazrs log an error before they raise it: the exception says it once."""

    def filter(self, record: logging.LogRecord) -> bool:
        return False


_QUIET = _DropLogRecords()


@contextlib.contextmanager
def _quiet_laspy() -> Iterator[None]:
    """laspy's log records (of its modules' loggers: a filter does not reach a child's records)
    dropped while a file is read or written here."""
    names = [n for n in list(logging.root.manager.loggerDict) if n.split(".")[0] == "laspy"]
    loggers = [logging.getLogger(name) for name in names]
    for logger in loggers:
        logger.addFilter(_QUIET)
    try:
        yield
    finally:
        for logger in loggers:
            logger.removeFilter(_QUIET)


def _laspy(path: object) -> Any:
    """Import laspy, or an :class:`InputError` naming ``path`` with the install command."""
    try:
        import laspy
    except ImportError as exc:
        raise InputError(
            path, f"reading LAS/LAZ needs laspy; install it with `{_INSTALL}`"
        ) from exc
    return laspy


def _is_laz(path: Path) -> bool:
    return path.suffix.lower() == ".laz"


def _problem(exc: BaseException, path: Path, header_read: bool) -> str:
    """A short phrase for what laspy or lazrs raised on a bad file (``header_read``: the
    header was fine, the point data was not)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if "LazBackend" in text or isinstance(exc, ImportError):  # no lazrs for compressed data
        return f"reading LAZ needs the lazrs backend; install it with `{_INSTALL}`"
    kind = "LAZ" if _is_laz(path) else "LAS"
    if header_read:
        return f"truncated or corrupt {kind} point data ({text})"
    return f"not a {kind} file ({text})"


class _Bounded:
    """A file whose ``read(n)`` never asks for more than is left of it: laspy reads a
    record's length from the file and allocates it before reading (a corrupt length of
    2**60 bytes is a MemoryError, or gigabytes of memory taken)."""

    def __init__(self, f: Any) -> None:
        self._f = f
        self._size = os.fstat(f.fileno()).st_size

    def read(self, n: int | None = -1) -> bytes:
        left = max(self._size - self._f.tell(), 0)
        return self._f.read(left if n is None or n < 0 or n > left else n)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._f, name)


def _check_public_header(f: Any, path: Path) -> None:
    """The counts and offsets of a LAS public header that laspy loops over or seeks to must
    fit the file before laspy reads it (a corrupt count of 4e9 records reads for hours).

    Raises:
        InputError: naming the file and the field that does not fit.
    """
    size = os.fstat(f.fileno()).st_size
    head = f.read(253)
    f.seek(0)
    if len(head) < 227 or head[:4] != b"LASF":
        raise InputError(path, "not a LAS file (no LASF header)")
    header_size, offset, vlrs = struct.unpack("<HII", head[94:104])
    if not header_size <= offset <= size:
        raise InputError(path, f"corrupt LAS header (point data at byte {offset} of {size})")
    if vlrs * 54 > offset - header_size:  # a VLR's own header is 54 bytes
        raise InputError(path, f"corrupt LAS header ({vlrs} records before byte {offset})")
    if head[24:26] >= bytes((1, 4)) and len(head) >= 247:
        start, evlrs = struct.unpack("<QI", head[235:247])
        if evlrs and (start > size or evlrs * 60 > size - start):  # 60: an EVLR's header
            raise InputError(path, f"corrupt LAS header ({evlrs} extended records at {start})")


def _check_data_size(f: Any, header: Any, path: Path) -> None:
    """An uncompressed file must hold the point records its header counts."""
    if header.are_points_compressed:
        return
    available = os.fstat(f.fileno()).st_size - header.offset_to_point_data
    need = header.point_count * header.point_format.size
    if available < need:
        found = max(available, 0) // max(header.point_format.size, 1)
        raise InputError(
            path,
            f"truncated LAS file (header says {header.point_count} points, the data holds {found})",
        )


def _bad_laz(path: Path, what: str) -> InputError:
    """The error of a LAZ file whose compressed points cannot be decoded, and why."""
    return InputError(path, f"truncated or corrupt LAZ point data ({what})")


def _check_chunks(f: Any, header: Any, path: Path) -> None:
    """A LAZ file's chunk size (its LASzip record) and chunk table must agree with the file
    and the header before lazrs decodes it: lazrs sizes its buffers by them and a corrupt
    value aborts the whole process on an allocation of tens of GB, which no ``except`` can
    catch. Leaves ``f`` where it was.

    Raises:
        InputError: naming the file and what does not agree.
    """
    if not header.are_points_compressed:
        return
    import lazrs

    record = next((v for v in header.vlrs if v.user_id == "laszip encoded"), None)
    if record is None:
        raise _bad_laz(path, "no LASzip record")
    position = f.tell()
    try:
        vlr = lazrs.LazVlr(record.record_data)
        chunk_size, count = int(vlr.chunk_size()), int(header.point_count)
        if chunk_size != _VARIABLE_CHUNKS and not 1 <= chunk_size <= MAX_CHUNK_POINTS:
            raise _bad_laz(path, f"chunks of {chunk_size} points")
        table = _chunk_table(f, header, vlr, path)
        points = [n for n, _ in table]
        if chunk_size != _VARIABLE_CHUNKS:
            want = math.ceil(count / chunk_size)
            points = [min(chunk_size, count - k * chunk_size) for k in range(len(table))]
            if len(table) != want:
                raise _bad_laz(path, f"chunk table: {len(table)} chunks for {count} points")
        if any(n < 1 or n > MAX_CHUNK_POINTS for n in points) or sum(points) != count:
            raise _bad_laz(path, f"chunk table: its chunks do not hold {count} points")
    except (lazrs.LazrsError, ValueError, struct.error) as exc:
        raise _bad_laz(path, f"chunk table: {exc}") from exc
    finally:
        f.seek(position)


def _chunk_table(f: Any, header: Any, vlr: Any, path: Path) -> list[tuple[int, int]]:
    """``[(points, bytes)]`` of each chunk of a LAZ file (``vlr``: its ``lazrs.LazVlr``),
    read by lazrs once the table's offset and chunk count are checked against the file."""
    import lazrs

    size = os.fstat(f.fileno()).st_size
    start = int(header.offset_to_point_data)
    f.seek(start)
    offset = struct.unpack("<q", f.read(8))[0]
    if offset == -1:  # a LAZ written to a stream: the offset is in the last 8 bytes
        f.seek(size - 8)
        offset = struct.unpack("<q", f.read(8))[0]
    if not start + 8 <= offset <= size - 8:
        raise _bad_laz(path, f"chunk table: at byte {offset} of {size}")
    f.seek(offset)
    version, chunks = struct.unpack("<II", f.read(8))
    # every chunk starts with one point stored raw: at least a point record's bytes each
    most = (offset - start - 8) // max(int(header.point_format.size), 1)
    if version != 0 or chunks > most:
        raise _bad_laz(path, f"chunk table: {chunks} chunks in {size} bytes")
    f.seek(start)
    table = [(int(n), int(b)) for n, b in lazrs.read_chunk_table(f, vlr)]
    if any(b < 1 for _, b in table) or sum(b for _, b in table) > offset - start - 8:
        raise _bad_laz(path, "chunk table: its chunks do not fit the file")
    return table


def read_las_points(path: str | os.PathLike[str]) -> np.ndarray:
    """x, y, z of every point of a LAS or LAZ file, the header's scales and offsets applied.

    Points are decoded in blocks, so the peak memory is about the ``(N, 3)`` float64 result
    plus one block of point records.

    Args:
        path: a ``.las`` or ``.laz`` file (LAS 1.0 to 1.4, any point format).

    Returns:
        ``(N, 3)`` float64 coordinates in the file's coordinate system (N >= 1).

    Raises:
        InputError: naming the file: missing, not a regular file, laspy (or lazrs for LAZ)
            not installed, not a LAS file, a header counting more points than byoc reads
            from one file, no points, truncated or corrupt point data.
    """
    path = Path(path)
    laspy = _laspy(path)
    header_read = False
    with open_input(path, "cloud") as f, _quiet_laspy():
        try:
            _check_public_header(f, path)
            with laspy.open(_Bounded(f), closefd=False) as reader:
                header = reader.header
                header_read = True
                count = int(header.point_count)
                if count == 0:
                    raise InputError(path, "empty point cloud (0 points)")
                check_point_count(count, path)
                _check_data_size(f, header, path)
                _check_chunks(f, header, path)
                out = np.empty((count, 3), dtype=np.float64)
                done = 0
                for chunk in reader.chunk_iterator(_CHUNK_POINTS):
                    n = min(len(chunk), count - done)
                    for j, axis in enumerate("xyz"):
                        out[done : done + n, j] = np.asarray(chunk[axis][:n], dtype=np.float64)
                    done += n
        except InputError:
            raise
        except MemoryError:
            raise
        except Exception as exc:  # laspy, lazrs and numpy raise many kinds on a bad file
            raise InputError(path, _problem(exc, path, header_read)) from exc
        except BaseException as exc:  # lazrs's Rust panics come as a BaseException
            if type(exc).__name__ != "PanicException":
                raise
            raise InputError(path, _problem(exc, path, header_read)) from exc
    if done < count:
        raise InputError(
            path, f"truncated LAS file (header says {count} points, the data holds {done})"
        )
    return out


def _offsets_for(points: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``offsets`` when every point fits LAS's int32 coordinates with them, else new offsets
    (the middle of the points' box, rounded to whole scale steps).

    Raises:
        ShapeError: the points span more than int32 steps of ``scales`` along an axis.
    """

    def fits(off: np.ndarray) -> bool:
        steps = np.round((points - off) / scales)
        return bool(np.all(steps >= _INT32[0]) and np.all(steps <= _INT32[1]))

    if fits(offsets):
        return offsets
    low, high = points.min(axis=0), points.max(axis=0)
    middle = np.round((low + high) / 2 / scales) * scales
    if not fits(middle):
        span = float(np.max((high - low) / scales))
        raise ShapeError(
            f"the moved points span {span:.3g} steps of the header's scales, more than LAS's "
            "int32 coordinates hold"
        )
    return middle


def write_las_like(
    path: str | os.PathLike[str], source: str | os.PathLike[str], points: np.ndarray
) -> None:
    """Write ``points`` as the coordinates of a copy of the LAS/LAZ file ``source``.

    The copy keeps the header (version, point format, VLRs and EVLRs such as the coordinate
    system, extra dimensions) and every point record; only x, y, z change. The header's scales
    are kept, and its offsets too while every new coordinate fits LAS's int32 range with them
    (else the offsets move to the middle of the new points). The header's bounds and counts
    are brought up to date by laspy. ``path`` ending in ``.laz`` is compressed, ``.las`` not.
    The file is written atomically.

    Args:
        path: the output (``.las`` or ``.laz``).
        source: the LAS/LAZ file the points were read from (:func:`read_las_points`).
        points: ``(N, 3)`` real, row k the new coordinates of the source's point k.

    Raises:
        InputError: ``source`` cannot be read (see :func:`read_las_points`), or ``path``
            cannot be written.
        ShapeError: ``points`` is not ``(N, 3)`` with N the source's point count, or the new
            coordinates do not fit LAS's int32 coordinates at the header's scales.
    """
    source = Path(source)
    laspy = _laspy(source)
    points = np.asarray(points, dtype=np.float64)
    with open_input(source, "cloud") as f, _quiet_laspy():
        try:
            las = laspy.read(f, closefd=False)
        except MemoryError:
            raise
        except Exception as exc:
            raise InputError(source, _problem(exc, source, False)) from exc
    count = len(las.points)
    if points.shape != (count, 3):
        raise ShapeError(f"points must be ({count}, 3) like {source}'s points, got {points.shape}")
    if not np.isfinite(points).all():
        raise ShapeError("points must be finite to be written as LAS coordinates")
    scales = np.asarray(las.header.scales, dtype=np.float64)
    las.header.offsets = _offsets_for(points, scales, np.asarray(las.header.offsets, np.float64))
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    with atomic_write(path, "wb") as out, write_errors(path), _quiet_laspy():
        try:
            las.write(out, do_compress=_is_laz(Path(path)))
        except OSError:
            raise
        except Exception as exc:  # lazrs missing for .laz, or an encoder failure
            text = " ".join(str(exc).split())
            if "LazBackend" in text or isinstance(exc, ImportError):
                raise InputError(
                    path, f"writing LAZ needs the lazrs backend; install it with `{_INSTALL}`"
                ) from exc
            raise InputError(path, f"cannot write it ({text})") from exc
