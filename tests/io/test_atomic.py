"""Atomic writes: the target is the old file or the complete new one, never a partial one."""

from __future__ import annotations

import os
import stat

import pytest

from byoc_cli.errors import InputError
from byoc_cli.io import atomic_write, atomic_write_bytes, atomic_write_text
from byoc_cli.io.atomic import write_errors


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_write_bytes_and_text(tmp_path):
    atomic_write_bytes(tmp_path / "a.bin", b"\x00\x01\xff")
    atomic_write_text(tmp_path / "b.txt", "héllo\n")
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01\xff"
    assert (tmp_path / "b.txt").read_bytes() == "héllo\n".encode()
    assert _leftovers(tmp_path) == []


def test_replaces_existing_file(tmp_path):
    path = tmp_path / "T.txt"
    path.write_text("old\n")
    with atomic_write(path, "w") as f:
        f.write("new\n")
        assert path.read_text() == "old\n"  # not visible before the block ends
    assert path.read_text() == "new\n"
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("exc_type", [RuntimeError, KeyboardInterrupt])
def test_exception_leaves_old_file_and_no_temp(tmp_path, exc_type):
    path = tmp_path / "T.txt"
    path.write_text("old\n")
    with pytest.raises(exc_type), atomic_write(path, "w") as f:
        f.write("half")
        raise exc_type("boom")
    assert path.read_text() == "old\n"
    assert _leftovers(tmp_path) == []


def test_exception_leaves_nothing_when_new(tmp_path):
    path = tmp_path / "new.ply"
    with pytest.raises(ValueError), atomic_write(path) as f:
        f.write(b"ply\n")
        raise ValueError("boom")
    assert list(tmp_path.iterdir()) == []


def test_fsync_failure_is_typed_and_cleaned(tmp_path, monkeypatch):
    path = tmp_path / "T.txt"
    path.write_text("old\n")

    def fail(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(InputError) as info:
        atomic_write_text(path, "new\n")
    assert info.value.path == str(path)
    assert "No space left on device" in info.value.problem
    assert path.read_text() == "old\n"
    assert _leftovers(tmp_path) == []


def test_write_error_in_body_is_typed(tmp_path):
    path = tmp_path / "x.bin"
    with pytest.raises(InputError, match="No space left"), atomic_write(path) as f:
        with write_errors(path):
            f.write(b"abc")
            raise OSError(28, "No space left on device")
    assert list(tmp_path.iterdir()) == []


def test_missing_folder(tmp_path):
    path = tmp_path / "nope" / "T.txt"
    with pytest.raises(InputError) as info:
        atomic_write_text(path, "x")
    assert str(info.value) == f"{path}: cannot write: the folder does not exist"


def test_target_is_directory(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(InputError) as info:
        atomic_write_text(tmp_path / "d", "x")
    assert info.value.path == str(tmp_path / "d")
    assert "cannot write" in info.value.problem
    assert _leftovers(tmp_path) == []


def test_bad_mode(tmp_path):
    with pytest.raises(ValueError, match="write mode"), atomic_write(tmp_path / "x", "r"):
        pass
    with (
        pytest.raises(ValueError, match="text modes"),
        atomic_write(tmp_path / "x", "wb", encoding="utf-8"),
    ):
        pass


def test_permissions_follow_umask_and_existing_file(tmp_path):
    old = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "new.txt", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "new.txt").stat().st_mode) == 0o644
    path = tmp_path / "exec.sh"
    path.write_text("old")
    path.chmod(0o750)
    atomic_write_text(path, "new")
    assert stat.S_IMODE(path.stat().st_mode) == 0o750


def test_symlink_is_written_through(tmp_path):
    real = tmp_path / "real.txt"
    real.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(real)
    atomic_write_text(link, "new")
    assert link.is_symlink()
    assert real.read_text() == "new"
