"""The output policy: what may be written, and all outputs of a run or none."""

from __future__ import annotations

import os

import pytest

from byoc_cli.errors import InputError
from byoc_cli.io import atomic_write_bytes, atomic_write_text
from byoc_cli.io.outputs import OutputSet, is_stdout


def test_stdout_and_none_pass_through(tmp_path):
    out = OutputSet()
    assert out.claim("-") is None and out.claim(None) is None
    assert is_stdout("-") and not is_stdout(tmp_path / "-x")


def test_refuses_inputs_links_to_them_and_files_in_input_folders(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    source = tmp_path / "s.ply"
    source.write_bytes(b"input")
    os.link(source, tmp_path / "hard.ply")
    os.symlink(source, tmp_path / "soft.ply")
    (data / "frame.png").write_bytes(b"frame")
    out = OutputSet(inputs=[source, None, "-"], input_dirs=[data])
    for path in (source, tmp_path / "hard.ply", tmp_path / "soft.ply"):
        with pytest.raises(InputError, match="input") as info:
            out.claim(path)
        assert info.value.path == str(path)
    with pytest.raises(InputError, match="inside the input folder"):
        out.claim(data / "frame.png")
    assert out.claim(data / "new.json") == data / "new.json"  # a new file there is fine


def test_one_scan_of_a_file_as_input_protects_the_file(tmp_path):
    site = tmp_path / "site.e57"
    site.write_bytes(b"scans")
    out = OutputSet(inputs=[f"{site}:2"])
    with pytest.raises(InputError, match="is an input of this run"):
        out.claim(site)


def test_refuses_folders_fifos_and_missing_folders(tmp_path):
    out = OutputSet()
    with pytest.raises(InputError, match="is a folder"):
        out.claim(tmp_path)
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "fifo")
        with pytest.raises(InputError, match="FIFO"):
            out.claim(tmp_path / "fifo")
    with pytest.raises(InputError, match="the folder does not exist"):
        out.claim(tmp_path / "no" / "T.txt")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="is not a folder"):
        out.claim(tmp_path / "file" / "T.txt")
    assert out.claim(tmp_path / "a.txt")
    with pytest.raises(InputError, match="named twice"):
        out.claim(tmp_path / "." / "a.txt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fifo", "file"] or not hasattr(
        os, "mkfifo"
    )


def test_commit_puts_every_output_in_place_at_the_end(tmp_path):
    a, b, other = tmp_path / "a.txt", tmp_path / "b.bin", tmp_path / "other.txt"
    a.write_text("old a")
    out = OutputSet()
    out.claim(a)
    out.claim(b)
    with out:
        atomic_write_text(a, "new a")
        atomic_write_bytes(b, b"new b")
        atomic_write_text(other, "not claimed: written at once")
        assert a.read_text() == "old a" and not b.exists()
        assert other.read_text() == "not claimed: written at once"
    assert a.read_text() == "new a" and b.read_bytes() == b"new b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.bin", "other.txt"]


def test_a_failing_run_changes_nothing(tmp_path):
    a = tmp_path / "a.txt"
    a.write_text("old a")
    out = OutputSet()
    out.claim(a)
    out.claim(tmp_path / "b.txt")
    with pytest.raises(RuntimeError), out:
        atomic_write_text(a, "new a")
        raise RuntimeError("the run failed after writing")
    assert a.read_text() == "old a"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_a_failing_commit_restores_the_replaced_files(tmp_path, monkeypatch):
    first, second, third = (tmp_path / n for n in ("1.txt", "2.txt", "3.txt"))
    first.write_text("old 1")
    third.write_text("old 3")
    out = OutputSet()
    for path in (first, second, third):
        out.claim(path)
    real_replace = os.replace

    def replace(src, dst, *args, **kwargs):
        if os.fspath(dst).endswith("3.txt") and os.fspath(src).endswith(".tmp"):
            raise OSError(28, "No space left on device")
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(InputError, match=r"3\.txt: cannot write"), out:
        for path in (first, second, third):
            atomic_write_text(path, f"new {path.name}")
    assert first.read_text() == "old 1" and third.read_text() == "old 3"
    assert not second.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["1.txt", "3.txt"]


@pytest.mark.parametrize(
    ("path", "phrase"),
    [
        ("/dev/stdout", "is standard output"),
        ("/dev/fd/1", "is standard output"),
        ("/dev/stderr", "is standard error"),
        ("/proc/self/fd/2", "is standard error"),
    ],
)
def test_the_standard_streams_named_as_files_are_refused_with_a_hint(path, phrase):
    assert is_stdout(path) == ("output" in phrase)  # /dev/stdout means stdout to the caller
    with pytest.raises(InputError, match=f"^{path}: {phrase}"):
        OutputSet().claim(path)
    assert OutputSet().claim("-") is None  # '-' is left to the caller
