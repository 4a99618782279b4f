"""The output policy of every command: what may be written, and all of it or nothing.

One :class:`OutputSet` per command run. Before the work starts, :meth:`OutputSet.claim`
checks each output file the user named and refuses (with :class:`InputError` naming it):

* an input of the same run (the same file, also through a link), or an existing file inside
  an input folder;
* anything that is not a regular file: a folder, a device node (``/dev/null``), a FIFO, a
  socket (``-`` is standard output and is left to the caller);
* the standard streams named as files (``/dev/stdout``, ``/dev/stderr``), with a hint: the
  caller turns ``/dev/stdout`` into ``-`` where an option takes it
  (:func:`byoc_cli.cli.output.claim_outputs`);
* a folder that does not exist or does not take new files (read-only, ``/proc``), found by
  creating and removing a probe file there;
* the same file named twice.

While the set is active (``with outputs:``), :func:`byoc_cli.io.atomic.atomic_write` hands
every complete temporary file of a claimed path to it instead of renaming it. When the block
ends normally, :meth:`OutputSet.commit` renames them all; a file that existed is first kept
as a hard link (or a renamed copy), and if any step fails every file already replaced is put
back to its previous bytes and the new ones are removed. When the block raises, the
temporaries are removed and nothing named by the user has changed.

The folders a command creates or fills (run folders, staging folders) are
:mod:`byoc_cli.io.folders`.
"""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from byoc_cli.errors import InputError
from byoc_cli.io.atomic import STAGER, temp_sibling, write_problem
from byoc_cli.io.cloudpath import cloud_file
from byoc_cli.io.inputs import file_kind

__all__ = ["OutputSet", "is_stdout"]


#: paths that name the standard streams of the process (Linux and macOS spellings)
STDOUT_PATHS = frozenset({"/dev/stdout", "/dev/fd/1", "/proc/self/fd/1"})
STDERR_PATHS = frozenset({"/dev/stderr", "/dev/fd/2", "/proc/self/fd/2"})


def is_stdout(path: str | os.PathLike[str] | None) -> bool:
    """True for the ``-`` that names standard output, and for ``/dev/stdout`` (and its
    spellings in :data:`STDOUT_PATHS`), which mean the same stream."""
    if path is None:
        return False
    return str(path) == "-" or os.path.normpath(str(path)) in STDOUT_PATHS


def is_stderr(path: str | os.PathLike[str] | None) -> bool:
    """True for ``/dev/stderr`` and its spellings in :data:`STDERR_PATHS`."""
    return path is not None and os.path.normpath(str(path)) in STDERR_PATHS


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.relative_to(folder)
    except ValueError:
        return False
    return True


def _probe(target: Path, shown: Path) -> None:
    """Create and remove a file beside ``target``: the folder must exist and take files."""
    parent = target.parent
    if not parent.exists():
        raise InputError(shown, "cannot write: the folder does not exist")
    if not parent.is_dir():
        raise InputError(shown, f"cannot write: {shown.parent} is not a folder")
    probe = temp_sibling(target, "probe")
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise InputError(shown, write_problem(exc, target)) from exc
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


class OutputSet:
    """The output files of one command run (see the module docstring).

    Args:
        inputs: files the run reads (missing ones are ignored).
        input_dirs: folders the run reads; an existing file inside one is never replaced.
    """

    def __init__(
        self,
        inputs: Iterable[str | os.PathLike[str] | None] = (),
        input_dirs: Iterable[str | os.PathLike[str] | None] = (),
    ) -> None:
        self._inputs: list[tuple[Path, tuple[int, int]]] = []
        self._input_dirs: list[Path] = []
        self.add_inputs(inputs, input_dirs)
        self._claimed: dict[Path, Path] = {}  # real target -> path as the user named it
        self._staged: dict[Path, Path] = {}  # real target -> complete temporary file
        self._removed: list[Path] = []  # files of an earlier run removed at commit
        self._token: Any = None

    def add_inputs(
        self,
        inputs: Iterable[str | os.PathLike[str] | None] = (),
        input_dirs: Iterable[str | os.PathLike[str] | None] = (),
    ) -> None:
        """Record more inputs (for instance the files a dataset folder turned out to hold)."""
        for path in inputs:
            if path is None or is_stdout(path):
                continue
            path = cloud_file(path)  # one scan of a multi-scan file (site.e57:2): the file
            identity = _identity(Path(path))
            if identity is not None:
                self._inputs.append((Path(path), identity))
        for folder in input_dirs:
            if folder is not None and Path(folder).is_dir():
                self._input_dirs.append(Path(os.path.realpath(folder)))

    def claim(self, path: str | os.PathLike[str] | None) -> Path | None:
        """Check that ``path`` may be written by this run; None and ``-`` pass through.

        Returns:
            ``path`` as a :class:`Path` (None for None and ``-``).

        Raises:
            InputError: naming ``path``, when the policy refuses it.
        """
        if path is None or str(path) == "-":
            return None
        shown = Path(path)
        if is_stdout(path):
            raise InputError(shown, "is standard output: name a file, or '-' where it is taken")
        if is_stderr(path):
            raise InputError(
                shown,
                "is standard error, which carries byoc's messages; name a file, or '-' where "
                "the option takes standard output",
            )
        target = Path(os.path.realpath(shown))  # a symlink is written through
        try:
            st = os.stat(target)
        except (FileNotFoundError, NotADirectoryError):
            st = None
        except OSError as exc:
            raise InputError(shown, write_problem(exc, target)) from exc
        if st is not None and not stat.S_ISREG(st.st_mode):
            raise InputError(shown, f"is {file_kind(st.st_mode)}; refusing to write over it")
        if st is not None:
            for source, identity in self._inputs:
                if identity == (st.st_dev, st.st_ino):
                    what = "an input" if source == shown else f"the input {source}"
                    raise InputError(shown, f"is {what} of this run; refusing to overwrite it")
            for folder in self._input_dirs:
                if _inside(target, folder):
                    raise InputError(
                        shown, f"is inside the input folder {folder}; refusing to overwrite it"
                    )
        if target in self._claimed:
            raise InputError(shown, f"is named twice (also as {self._claimed[target]})")
        _probe(target, shown)
        self._claimed[target] = shown
        return shown

    def remove(self, path: str | os.PathLike[str]) -> None:
        """Remove ``path`` (a stale output of an earlier run of the same command) when the
        set commits, with the same all-or-nothing guarantee as the files written.

        Raises:
            InputError: ``path`` is claimed by this run, or is not a regular file.
        """
        target = Path(os.path.realpath(path))
        if target in self._claimed:
            raise InputError(path, "is an output of this run; cannot also remove it")
        if not target.is_file():
            raise InputError(path, "is not a regular file; refusing to remove it")
        self._removed.append(target)

    # ------------------------------------------------------------------ transaction

    def _stage(self, target: Path, temp: Path) -> bool:
        real = Path(os.path.realpath(target))
        if real not in self._claimed:
            return False
        previous = self._staged.pop(real, None)
        if previous is not None:
            with contextlib.suppress(OSError):
                os.unlink(previous)
        self._staged[real] = temp
        return True

    def __enter__(self) -> OutputSet:
        self._token = STAGER.set(self._stage)
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        STAGER.reset(self._token)
        if exc_type is None:
            self.commit()
        else:
            self.discard()

    def discard(self) -> None:
        """Remove every staged temporary file; nothing the user named changes."""
        for temp in self._staged.values():
            with contextlib.suppress(OSError):
                os.unlink(temp)
        self._staged.clear()

    def commit(self) -> None:
        """Put every staged file in place and remove the files given to :meth:`remove`, all
        of it or (on failure) none.

        Raises:
            InputError: a rename failed; every file replaced so far has its old bytes back.
        """
        done: list[tuple[Path, Path | None]] = []  # (target, backup or None when it was new)
        try:
            for target, temp in list(self._staged.items()):
                backup = _keep_backup(target)
                try:
                    os.replace(temp, target)
                except OSError as exc:
                    if backup is not None:  # target untouched: drop its second name
                        with contextlib.suppress(OSError):
                            os.unlink(backup)
                    raise InputError(self._claimed[target], write_problem(exc, target)) from exc
                done.append((target, backup))
                del self._staged[target]
            for target in self._removed:
                backup = _keep_backup(target)
                try:
                    os.unlink(target)
                except FileNotFoundError:
                    pass
                except OSError as exc:
                    if backup is not None:
                        with contextlib.suppress(OSError):
                            os.unlink(backup)
                    raise InputError(target, f"cannot remove it ({exc.strerror or exc})") from exc
                done.append((target, backup))
            self._removed.clear()
        except BaseException:
            _roll_back(done)
            self.discard()
            raise
        for _, backup in done:
            if backup is not None:
                with contextlib.suppress(OSError):
                    os.unlink(backup)
        for folder in {target.parent for target, _ in done}:
            _fsync_folder(folder)


def _keep_backup(target: Path) -> Path | None:
    """A second name for the current ``target`` (hard link, else a copy); None when new."""
    if not target.exists():
        return None
    backup = temp_sibling(target, "bak")
    try:
        os.link(target, backup)
    except OSError:
        import shutil

        try:
            shutil.copy2(target, backup)
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.unlink(backup)
            raise InputError(target, f"cannot keep a backup before replacing it ({exc})") from exc
    return backup


def _roll_back(done: list[tuple[Path, Path | None]]) -> None:
    for target, backup in reversed(done):
        with contextlib.suppress(OSError):
            if backup is None:
                os.unlink(target)
            else:
                os.replace(backup, target)


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    with contextlib.suppress(OSError):
        os.fsync(fd)
    os.close(fd)
