"""The folders a command creates or fills, all of them or none, and what killed runs left.

:func:`check_run_folder` is the policy for a command that fills a folder (``train --out``):
only a new or empty folder, or one the tool recognises as its own; :func:`mark_folder` makes a
folder the tool's own from the moment it creates it, so a killed run can be run again.
:func:`new_folders` creates folders (and parents) and removes them when the block fails;
:class:`StagingFolder` is a locked hidden folder renamed into place at the end, and
:func:`remove_stale_staging` removes the ones killed runs left;
:func:`remove_stale_temporaries` removes the temporary files of :mod:`byoc_cli.io.atomic` and
:class:`byoc_cli.io.outputs.OutputSet` that killed runs left in a folder the command owns.
The output files themselves are :mod:`byoc_cli.io.outputs`.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from pathlib import Path

from byoc_cli.errors import InputError
from byoc_cli.io.atomic import temp_prefix, temp_sibling, write_problem

__all__ = [
    "StagingFolder",
    "check_run_folder",
    "is_marked",
    "mark_folder",
    "new_folders",
    "remove_stale_staging",
    "remove_stale_temporaries",
]


def check_run_folder(
    folder: str | os.PathLike[str], is_own: Callable[[Path], bool], what: str = "run folder"
) -> None:
    """Refuse a folder that a command would fill unless it is new, empty or the tool's own.

    Args:
        folder: the folder to be created or written into.
        is_own: tells a folder the tool wrote (e.g. by a marker file it recognises).
        what: how the folder is called in the message.

    Raises:
        InputError: ``folder`` is a file, or a non-empty folder that is not the tool's.
    """
    folder = Path(folder)
    if not folder.exists():
        if folder.is_symlink():
            raise InputError(folder, f"is a dangling link; give a new or empty {what}")
        return
    if not folder.is_dir():
        raise InputError(folder, f"is not a folder; give a new or empty {what}")
    try:
        entries = sorted(p.name for p in folder.iterdir())
    except OSError as exc:
        raise InputError(folder, f"cannot list it ({exc.strerror or exc})") from exc
    if not entries or is_own(folder):
        return
    shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
    raise InputError(
        folder,
        f"is not empty and not a byoc {what} (holds {shown}); refusing to write into it "
        f"(give a new or empty folder)",
    )


@contextlib.contextmanager
def new_folders(*folders: str | os.PathLike[str]) -> Iterator[list[Path]]:
    """Create the missing ``folders`` (and their missing parents, in order); when the block
    raises, remove every folder created here that is empty again, innermost first.

    ``register-batch --out-dir x/y/z`` refused for bad input leaves neither ``x/y/z`` nor
    ``x/y``. Yields the folders created.

    Raises:
        InputError: a folder cannot be created (naming it).
    """
    created: list[Path] = []
    try:
        for folder in folders:
            missing = []
            path = Path(folder)
            while not path.exists() and not path.is_symlink() and path != path.parent:
                missing.append(path)
                path = path.parent
            for path in reversed(missing):
                try:
                    path.mkdir()
                except FileExistsError:
                    continue
                except OSError as exc:
                    raise InputError(path, write_problem(exc, path)) from exc
                created.append(path)
        yield created
    except BaseException:
        for path in reversed(created):
            with contextlib.suppress(OSError):
                path.rmdir()
        raise


#: The file that marks a folder as a command's own from the moment the command creates it
#: (``.byoc-<command>``): a run killed before it wrote anything can be run again.
MARKER_PREFIX = ".byoc-"


def mark_folder(folder: str | os.PathLike[str], command: str) -> Path:
    """Mark ``folder`` as ``command``'s own (the marker is an empty hidden file).

    Raises:
        InputError: the marker cannot be written.
    """
    marker = Path(folder) / f"{MARKER_PREFIX}{command}"
    try:
        marker.touch()
    except OSError as exc:
        raise InputError(marker, write_problem(exc, marker)) from exc
    return marker


def is_marked(folder: str | os.PathLike[str], command: str) -> bool:
    """True when ``folder`` holds ``command``'s marker (see :func:`mark_folder`)."""
    return (Path(folder) / f"{MARKER_PREFIX}{command}").is_file()


# ---------------------------------------------------------------- staging folders


class StagingFolder:
    """A new hidden folder beside ``target`` (``.<name>.<8 hex>.tmp``), locked while it lives.

    A command that fills ``target`` writes into it and renames it to ``target`` at the end.
    The folder's descriptor holds an exclusive ``flock`` as long as the process runs; a
    process that is killed loses its lock, so :func:`remove_stale_staging` can tell a
    leftover from a folder in use and remove it on the next run.

    Raises:
        InputError: the folder cannot be created.
    """

    def __init__(self, target: str | os.PathLike[str]) -> None:
        self.target = Path(target)
        self.path = temp_sibling(self.target, "tmp")
        try:
            self.path.mkdir()
        except OSError as exc:
            raise InputError(self.target, write_problem(exc, self.path)) from exc
        self._fd = _lock(self.path)

    def release(self) -> None:
        """Drop the lock (the folder has been renamed or removed)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _lock(folder: Path) -> int | None:
    """An open descriptor of ``folder`` holding an exclusive lock; None when the lock is
    taken or locks are not available here."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no stale-folder detection
        return None
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def remove_stale_staging(target: str | os.PathLike[str]) -> list[Path]:
    """Remove the staging folders of ``target`` left by killed runs (see
    :class:`StagingFolder`): hidden ``.<name>.<8 hex>.tmp`` folders beside it whose lock no
    live process holds. Returns those removed."""
    import re
    import shutil

    target = Path(target)
    pattern = re.compile(re.escape(temp_prefix(target, "tmp")) + r"\.[0-9a-f]{8}\.tmp")
    try:
        entries = list(target.parent.iterdir()) if target.parent.is_dir() else []
    except OSError:
        return []
    removed = []
    for entry in entries:
        if not (pattern.fullmatch(entry.name) and entry.is_dir() and not entry.is_symlink()):
            continue
        fd = _lock(entry)
        if fd is None:  # in use by a running command (or no locks here): leave it
            continue
        try:
            shutil.rmtree(entry, ignore_errors=True)
        finally:
            os.close(fd)
        removed.append(entry)
    return removed


#: The temporary files of :mod:`byoc_cli.io.atomic` and of
#: :class:`byoc_cli.io.outputs.OutputSet`.
_TEMPORARY = r"\..+\.[0-9a-f]{8}\.(tmp|bak|probe)"


def remove_stale_temporaries(folder: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporary files a killed run left in ``folder``, a folder the command owns
    (``.<name>.<8 hex>.tmp``, ``.bak``, ``.probe``: names only byoc gives). Returns them."""
    import re

    pattern = re.compile(_TEMPORARY)
    removed = []
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return []
    for entry in entries:
        if pattern.fullmatch(entry.name) and entry.is_file() and not entry.is_symlink():
            with contextlib.suppress(OSError):
                entry.unlink()
                removed.append(entry)
    return removed
