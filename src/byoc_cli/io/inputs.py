"""Opening the files byoc reads: regular files only, never blocking, a size cap per kind.

Every reader of byoc-cli opens the file it parses through :func:`open_input` (or reads it
whole through :func:`read_input`). The path is looked at (``stat``) before it is opened, and
opened with ``O_NONBLOCK``, so a FIFO, a device such as ``/dev/zero``, a socket or a folder
is refused without a byte read and without blocking; then the file must be a regular file
no larger than the cap of its kind (:data:`SIZE_CAPS`). A whole-file read stops at the cap
plus one byte, so a file that grows while it is read cannot take more memory either.

The caps bound what reading one input may cost, whatever a hostile file claims: text kinds
are parsed into Python objects (tens of bytes per line), so their caps are small; clouds are
bounded further by their point count (:data:`MAX_CLOUD_POINTS`, checked by the readers from
the header before the points are allocated).
"""

from __future__ import annotations

import json
import os
import stat
from typing import Any, BinaryIO

from byoc_cli.errors import InputError

__all__ = [
    "MAX_CLOUD_POINTS",
    "MAX_OPEN3D_POINTS",
    "SIZE_CAPS",
    "check_input",
    "check_point_count",
    "file_kind",
    "format_size",
    "open_input",
    "read_input",
    "read_json_input",
]

KiB = 1024
MiB = 1024 * KiB
GiB = 1024 * MiB

#: kind of input -> (largest size accepted in bytes, how the kind is named in messages)
SIZE_CAPS: dict[str, tuple[int, str]] = {
    # binary PLY and NPY are read in chunks; MAX_CLOUD_POINTS bounds their memory
    "cloud": (8 * GiB, "a point-cloud file"),
    # PLY with list properties before the vertices: plyfile reads the whole file as objects
    "cloud-general": (64 * MiB, "a PLY file with list properties before its vertices"),
    # PCD and XYZ/PTS: open3d reads the whole file (convert larger ones to binary PLY)
    "cloud-open3d": (128 * MiB, "a PCD or XYZ file"),
    "weights": (512 * MiB, "a weights file"),
    "checkpoint": (2 * GiB, "a training checkpoint"),
    "pair list": (32 * MiB, "a pair list"),
    "config": (1 * MiB, "a config file"),
    # a registration recipe is a few hundred bytes; the cap leaves room for a hostile file to
    # reach the scan of io/tomlfile.py, which names the key it refuses
    "recipe": (1 * MiB, "a recipe file"),
    "benchmark": (64 * MiB, "a gt.log, gt.info or gt_overlap.log file"),
    "trajectory": (32 * MiB, "a trajectory file"),
    "image": (256 * MiB, "an image"),
    "intrinsics": (1 * MiB, "an intrinsics file"),
    "matrix": (1 * MiB, "a matrix file"),
    "listing": (64 * MiB, "a frame listing"),
    "report": (256 * MiB, "a report or run file"),
    "cache": (2 * GiB, "a feature cache entry"),
}

#: Most points read from one cloud file (a float64 copy is 24 bytes a point: 720 MB).
MAX_CLOUD_POINTS = 30_000_000
#: Most points open3d may read from one PCD file (it keeps its own copy besides ours).
MAX_OPEN3D_POINTS = 15_000_000


def check_point_count(count: int, path: object, limit: int = MAX_CLOUD_POINTS) -> None:
    """Refuse a cloud whose header claims more than ``limit`` points, before reading them.

    Raises:
        InputError: naming ``path`` and the limit.
    """
    if count > limit:
        raise InputError(
            path,
            f"holds {count:,} points, more than byoc reads from one file ({limit:,}); "
            "downsample it first",
        )


def format_size(size: int) -> str:
    """``size`` bytes in the largest binary unit that keeps it >= 1 (``512 MiB``)."""
    for unit, scale in (("GiB", GiB), ("MiB", MiB), ("KiB", KiB)):
        if size >= scale:
            value = size / scale
            return f"{value:.0f} {unit}" if value == int(value) else f"{value:.1f} {unit}"
    return f"{size} bytes"


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, as a phrase (``a FIFO``, ``a device``, ...)."""
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISREG(mode):
        return "a regular file"
    return "not a regular file"


def _check(st: os.stat_result, path: object, kind: str, error: type[InputError]) -> None:
    """Refuse what is not a regular file, and a regular file larger than ``kind``'s cap."""
    if stat.S_ISDIR(st.st_mode):
        raise error(path, "is a directory")
    if not stat.S_ISREG(st.st_mode):
        raise error(path, f"is {file_kind(st.st_mode)}, not a regular file; refusing to read it")
    cap, what = SIZE_CAPS[kind]
    if st.st_size > cap:
        raise error(
            path,
            f"is {format_size(st.st_size)}, larger than {what} may be ({format_size(cap)})",
        )


def _os_problem(exc: OSError) -> str:
    if isinstance(exc, FileNotFoundError | NotADirectoryError):
        return "no such file"
    if isinstance(exc, IsADirectoryError):
        return "is a directory"
    if isinstance(exc, PermissionError):
        return "permission denied"
    return f"cannot read: {exc.strerror or exc}"


def check_input(
    path: str | os.PathLike[str], kind: str, error: type[InputError] = InputError
) -> None:
    """Check, without opening it, that ``path`` is a regular file within ``kind``'s cap: for
    readers that open the file themselves by name (pillow, open3d).

    Raises:
        error: as :func:`open_input`.
    """
    try:
        st = os.stat(path)
    except OSError as exc:
        raise error(path, _os_problem(exc)) from exc
    _check(st, path, kind, error)


def _open_fd(path: str | os.PathLike[str]) -> int:
    """A read-only descriptor of ``path``, opened without blocking (a FIFO never waits)."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    return os.open(path, flags | getattr(os, "O_BINARY", 0))


def open_input(
    path: str | os.PathLike[str], kind: str, error: type[InputError] = InputError
) -> BinaryIO:
    """Open ``path`` for binary reading if it is a regular file within ``kind``'s cap.

    Args:
        path: the input file (a symlink is followed).
        kind: a key of :data:`SIZE_CAPS` (``"cloud"``, ``"weights"``, ``"pair list"``, ...).
        error: the :class:`InputError` subclass raised (``WeightsError``, ``DatasetError``).

    Returns:
        The open file, at its start, in blocking mode.

    Raises:
        error: naming ``path``: "no such file", "is a directory", "permission denied",
            "is a FIFO, not a regular file", "is 5 GiB, larger than a weights file may be",
            "cannot read: <reason>".
    """
    try:
        _check(os.stat(path), path, kind, error)  # before open: a FIFO is never opened
        fd = _open_fd(path)
    except OSError as exc:
        raise error(path, _os_problem(exc)) from exc
    try:
        _check(os.fstat(fd), path, kind, error)  # the file that was opened, not a swapped one
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_input(
    path: str | os.PathLike[str], kind: str, error: type[InputError] = InputError
) -> bytes:
    """The whole content of ``path`` (see :func:`open_input`), never more than ``kind``'s cap.

    Raises:
        error: as :func:`open_input`; also when the file grew past the cap while read.
    """
    cap, what = SIZE_CAPS[kind]
    with open_input(path, kind, error) as f:
        try:
            data = f.read(cap + 1)
        except OSError as exc:
            raise error(path, _os_problem(exc)) from exc
    if len(data) > cap:
        raise error(path, f"is larger than {what} may be ({format_size(cap)})")
    return data


def read_json_input(
    path: str | os.PathLike[str], kind: str = "report", error: type[InputError] = InputError
) -> Any:
    """The JSON document in ``path`` (see :func:`read_input`).

    Raises:
        error: as :func:`read_input`, or "not valid JSON (...)".
    """
    try:
        return json.loads(read_input(path, kind, error).decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:  # JSONDecodeError, nesting too deep
        raise error(path, f"not valid JSON ({exc})") from exc
    except RecursionError as exc:
        raise error(path, "not valid JSON (nested too deeply)") from exc
