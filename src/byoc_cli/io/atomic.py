"""Atomic file writes: a file at ``path`` is either the old one or the complete new one.

Every writer in byoc-cli (transforms, PLY files, JSON reports, checkpoints, weights) goes
through :func:`atomic_write`: the data goes to a temporary file in the same directory, is
flushed and fsynced, and only then renamed over ``path`` with :func:`os.replace` (atomic on
POSIX and on Windows within one volume). On any exception the temporary file is removed and
``path`` is left untouched.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import secrets
import stat
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

from byoc_cli.errors import InputError

__all__ = [
    "STAGER",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "temp_sibling",
    "write_errors",
    "write_problem",
]

_WRITE_MODES = {"w", "wt", "wb", "w+", "w+t", "w+b", "wb+", "wt+"}

#: Set by :class:`byoc_cli.io.outputs.OutputSet` while a command runs: called with
#: ``(target, temp)`` once a temporary file is complete; returns True when it takes the
#: temporary over (to rename it at the end of the run, with the other outputs), False when
#: ``target`` is not one of its outputs (then it is renamed at once, as usual).
STAGER: contextvars.ContextVar[Callable[[Path, Path], bool] | None] = contextvars.ContextVar(
    "byoc_output_stager", default=None
)


def _target(path: str | os.PathLike[str]) -> Path:
    """The file that will be replaced: a symlink is written through, not replaced."""
    path = Path(path)
    if path.is_symlink():
        return Path(os.path.realpath(path))
    return path


#: Longest file name in bytes when the file system does not say (most allow 255).
DEFAULT_NAME_MAX = 255


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):  # no such folder (yet), or not POSIX
        return DEFAULT_NAME_MAX


def temp_prefix(target: Path, suffix: str) -> str:
    """``.<name>`` of the temporary names of ``target`` (see :func:`temp_sibling`), the name
    cut (in bytes) so that ``.<name>.<8 hex>.<suffix>`` fits the folder's name limit: a
    legal 250-byte name still gets a temporary beside it."""
    room = _name_max(target.parent) - len(f"..{'0' * 8}.{suffix}".encode())
    return "." + os.fsdecode(os.fsencode(target.name)[: max(room, 1)])


def temp_sibling(target: Path, suffix: str) -> Path:
    """A new hidden name ``.<name>.<8 hex>.<suffix>`` beside ``target`` (not created)."""
    return target.with_name(f"{temp_prefix(target, suffix)}.{secrets.token_hex(4)}.{suffix}")


def _create_temp(target: Path) -> tuple[int, Path]:
    """Create ``.<name>.<random>.tmp`` beside ``target``; returns ``(fd, temp_path)``.

    ``os.open`` with mode 0o666 lets the process umask decide the permissions, as for a
    file created by ``open()``; an existing target's permission bits are kept.
    """
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        temp = temp_sibling(target, "tmp")
        try:
            fd = os.open(temp, flags, 0o666)
        except FileExistsError:
            continue
        try:
            st = os.stat(target)
        except OSError:
            pass
        else:
            if stat.S_ISREG(st.st_mode):
                with contextlib.suppress(OSError):
                    os.chmod(temp, stat.S_IMODE(st.st_mode))
        return fd, temp
    raise FileExistsError(f"could not create a temporary file beside {target}")


def _fsync_directory(directory: Path) -> None:
    """Make the rename durable; silently skipped where directories cannot be fsynced."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_problem(exc: OSError, path: str | os.PathLike[str] | None = None) -> str:
    """A short phrase for an ``OSError`` raised while creating or writing ``path``."""
    if isinstance(exc, FileNotFoundError):
        parent = Path(path).parent if path is not None else None
        if parent is not None and parent.is_dir():
            return f"cannot write: the file system of {parent} does not accept new files"
        return "cannot write: the folder does not exist"
    if exc.errno == errno.EROFS:
        return "cannot write: read-only file system"
    if isinstance(exc, PermissionError):
        return "cannot write: permission denied"
    if isinstance(exc, IsADirectoryError):
        return "cannot write: is a directory"
    return f"cannot write: {exc.strerror or exc}"


@contextlib.contextmanager
def write_errors(path: str | os.PathLike[str]) -> Iterator[None]:
    """Turn an ``OSError`` raised while writing ``path`` (disk full, I/O error) into
    :class:`InputError` naming ``path``; use inside an :func:`atomic_write` block."""
    try:
        yield
    except OSError as exc:
        raise InputError(path, write_problem(exc, path)) from exc


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike[str],
    mode: str = "wb",
    *,
    encoding: str | None = None,
    newline: str | None = None,
) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path``; on success it atomically replaces ``path``.

    Usage::

        with atomic_write(path, "w") as f:
            f.write(text)

    The temporary file (``.<name>.<random>.tmp`` in the same folder) is flushed, fsynced and
    renamed over ``path`` when the block exits normally; when the block (or the flush) raises,
    it is removed and ``path`` is left as it was, so nothing half-written is ever visible at
    ``path``. A symlink at ``path`` is written through (its target is replaced). The new file
    gets the permissions of the file it replaces, or those set by the umask.

    Args:
        path: the file to write.
        mode: a write mode, ``"wb"`` (default) or ``"w"``/``"wt"`` for text.
        encoding: text encoding for text modes (default UTF-8); must be None for binary.
        newline: passed to :func:`open` for text modes.

    Yields:
        The open temporary file.

    Raises:
        ValueError: ``mode`` is not a write mode.
        InputError: the file cannot be created or replaced (missing folder, permission
            denied, ``path`` is a directory); the problem names ``path``.
        Any exception raised inside the block is re-raised unchanged after cleanup.
    """
    if mode not in _WRITE_MODES:
        raise ValueError(f"atomic_write needs a write mode ('w', 'wb', ...), got {mode!r}")
    binary = "b" in mode
    if binary and (encoding is not None or newline is not None):
        raise ValueError("encoding and newline are for text modes only")
    if not binary and encoding is None:
        encoding = "utf-8"
    target = _target(path)
    try:
        fd, temp = _create_temp(target)
    except OSError as exc:
        raise InputError(path, write_problem(exc, path)) from exc
    f = os.fdopen(fd, mode, encoding=encoding, newline=newline)
    try:
        yield f
        try:
            f.flush()
            os.fsync(f.fileno())
            f.close()
        except OSError as exc:  # disk full, quota, I/O error
            raise InputError(path, write_problem(exc, path)) from exc
        stager = STAGER.get()
        if stager is not None and stager(target, temp):
            return
        try:
            os.replace(temp, target)
        except OSError as exc:
            raise InputError(path, write_problem(exc, path)) from exc
    except BaseException:
        # closing flushes again, which fails again on a full disk: never let that hide the error
        with contextlib.suppress(OSError, ValueError):
            f.close()
        with contextlib.suppress(OSError):
            os.unlink(temp)
        raise
    _fsync_directory(target.parent)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes | bytearray | memoryview) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_write`).

    Raises:
        InputError: the file cannot be created or replaced.
    """
    with atomic_write(path, "wb") as f, write_errors(path):
        f.write(data)


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_write`).

    Raises:
        InputError: the file cannot be created or replaced.
    """
    with atomic_write(path, "w", encoding=encoding) as f, write_errors(path):
        f.write(text)
