"""The numbered cases of issue 12 ("never lose a user's file; every bad input a one-line
error"), each as the user ran it: through the CLI, checking the exit code, that stderr is one
line naming the file (or the option), and that no file the user had was changed."""

from __future__ import annotations

import json
import os
import stat
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli
from byoc_cli.io import write_ply


def _run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def _one_error_line(result, code: int = 1) -> str:
    """The single ``byoc: error:`` line of a failed run (no traceback, nothing else)."""
    assert result.exit_code == code, (result.exit_code, result.output, result.exception)
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("byoc: error: "), lines[0]
    return lines[0]


def _usage_error(result, option: str) -> None:
    assert result.exit_code == 2, (result.output, result.exception)
    assert "Traceback" not in result.output
    assert f"'{option}'" in result.stderr, result.stderr


def _box(n: int = 1500, seed: int = 0) -> np.ndarray:
    """Points on the faces of a 3 x 2 x 1.6 m box."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = np.sign(pts[np.arange(n), axis])
    return pts * np.array([1.5, 1.0, 0.8])


@pytest.fixture
def pair(tmp_path: Path) -> tuple[Path, Path]:
    src, tgt = tmp_path / "s.ply", tmp_path / "t.ply"
    pts = _box()
    write_ply(src, pts)
    write_ply(tgt, pts + np.array([0.1, 0.0, 0.05]))
    return src, tgt


def _register(src, tgt, *args):
    return _run("register", src, tgt, "--features", "fpfh", *args)


# ---------------------------------------------------------------------------- 1-5 data loss


def _device_node(path: Path) -> bool:
    """A character device like /dev/null at ``path`` (a test must never risk the real one)."""
    try:
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    except (AttributeError, OSError):
        return False
    return True


def test_case1_device_node_and_fifo_are_never_replaced(pair, tmp_path):
    device = tmp_path / "null"
    if _device_node(device):
        line = _one_error_line(_register(*pair, "-o", device))
        assert str(device) in line and "device" in line
        assert stat.S_ISCHR(os.stat(device).st_mode)
    if hasattr(os, "mkfifo"):
        fifo = tmp_path / "pipe"
        os.mkfifo(fifo)
        line = _one_error_line(_register(*pair, "--json", fifo))
        assert str(fifo) in line and "FIFO" in line
        assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    if not device.exists() and not hasattr(os, "mkfifo"):
        pytest.skip("cannot create a device node or a FIFO here")


def test_case2_output_over_an_input_is_refused(pair):
    src, tgt = pair
    before = src.read_bytes()
    line = _one_error_line(_register(src, tgt, "-o", src))
    assert str(src) in line and "input" in line
    assert src.read_bytes() == before
    # also through another name of the same file
    link = src.with_name("alias.ply")
    os.link(src, link)
    line = _one_error_line(_register(src, tgt, "--aligned", link))
    assert "input" in line and src.read_bytes() == before


def test_case3_a_failed_run_restores_what_it_would_replace(pair, tmp_path):
    src, tgt = pair
    before = src.read_bytes()
    result = _register(src, tgt, "--aligned", src, "-o", tmp_path / "missing_dir" / "T.txt")
    _one_error_line(result)
    assert src.read_bytes() == before
    # an earlier aligned cloud (not an input) survives a run that fails at -o
    aligned = tmp_path / "aligned.ply"
    aligned.write_bytes(b"the user's file")
    result = _register(src, tgt, "--aligned", aligned, "-o", tmp_path / "missing_dir" / "T.txt")
    assert "the folder does not exist" in _one_error_line(result)
    assert aligned.read_bytes() == b"the user's file"


def test_case4_unwritable_output_keeps_the_previous_report(pair, tmp_path):
    keep = tmp_path / "keep"
    keep.mkdir()
    report = keep / "report.json"
    report.write_text('{"previous": true}\n')
    # /proc takes no new files (a read-only place that even root cannot write into)
    if Path("/proc").is_dir():
        _one_error_line(_register(*pair, "--json", report, "-o", "/proc/T.txt"))
        assert report.read_text() == '{"previous": true}\n'
    # a commit that fails half-way (the rename of T fails after the report was replaced)
    out = tmp_path / "T.txt"
    real_replace = os.replace

    def failing_replace(a, b, *args, **kwargs):
        if Path(b).name == "T.txt":
            raise OSError(30, "Read-only file system")
        return real_replace(a, b, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "replace", failing_replace)
        line = _one_error_line(_register(*pair, "--json", report, "-o", out))
    assert "T.txt" in line
    assert report.read_text() == '{"previous": true}\n' and not out.exists()
    assert sorted(p.name for p in keep.iterdir()) == ["report.json"]


@pytest.mark.realdata
def test_case5_train_refuses_a_folder_it_did_not_create(shared_data, tmp_path):
    run = tmp_path / "mine"
    (run / "checkpoints").mkdir(parents=True)
    files = {
        run / "weights.safetensors": b"my weights",
        run / "training.png": b"my plot",
        run / "checkpoints" / "step-00000005.pt": b"my checkpoint",
    }
    for path, data in files.items():
        path.write_bytes(data)
    args = ["train", "--rgbd-dir", shared_data / "rgbd" / "tum_fr1_xyz", "--steps", "1"]
    args += ["--batch-size", "1", "--val-every", "0", "--num-workers", "0", "--quiet"]
    args += ["--variant", "byoc-geo", "--device", "cpu", "--view-spacing", "2"]
    line = _one_error_line(_run(*args, "--out", run))
    assert str(run) in line and "not empty" in line
    assert all(path.read_bytes() == data for path, data in files.items())
    assert sorted(p.name for p in run.iterdir()) == [
        "checkpoints",
        "training.png",
        "weights.safetensors",
    ]
    # a file given as --out is refused too; a new folder is accepted
    _one_error_line(_run(*args, "--out", run / "training.png"))
    fresh = tmp_path / "fresh"
    result = _run(*args, "--out", fresh)
    assert result.exit_code == 0, result.stderr
    assert (fresh / "config.json").is_file()


# ---------------------------------------------------------------------------- 6-7 resources


def _weights_with(tmp_path: Path, name: str, edit) -> Path:
    """A valid random-init weights file whose metadata ``edit`` changes (and may replace
    the tensors); the checksum is recomputed so that only the edit is wrong."""
    from safetensors.torch import load, save

    from byoc_cli.pipeline.weights import tensors_sha256

    good = tmp_path / "good.safetensors"
    if not good.exists():
        assert _run("weights", "init", "-o", good).exit_code == 0
    blob = good.read_bytes()
    (n,) = struct.unpack("<Q", blob[:8])
    meta = json.loads(json.loads(blob[8 : 8 + n])["__metadata__"]["byoc"])
    tensors = load(blob)
    tensors = edit(meta, tensors) or tensors
    meta["tensors_sha256"] = tensors_sha256(tensors)
    path = tmp_path / name
    path.write_bytes(save(tensors, metadata={"byoc": json.dumps(meta)}))
    return path


def test_case6_absurd_architecture_is_refused_before_allocation(tmp_path):
    import torch

    def huge(meta, tensors):
        meta["architecture_config"]["encoder_channels"] = [1_000_000] * 4
        return {"w": torch.zeros(1)}

    path = _weights_with(tmp_path, "huge.safetensors", huge)
    assert path.stat().st_size < 2000
    line = _one_error_line(_run("weights", "info", path))
    assert str(path) in line and "architecture_config" in line and "encoder_channels" in line


def _intrinsics(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_case7_tracebacks_become_one_line(tmp_path):
    from PIL import Image

    depth = tmp_path / "d.png"
    Image.fromarray(np.full((24, 32), 1000, dtype=np.uint16)).save(depth)
    tiny = _intrinsics(tmp_path, "tiny.txt", "1e-7 0 16\n0 1e-7 12\n0 0 1\n")
    line = _one_error_line(
        _run("register", depth, depth, "--features", "fpfh", "--intrinsics", tiny)
    )
    assert str(tiny) in line and "focal" in line
    K = [500, 0, 0, 0, 500, 0, 16, 12, 1]
    wide = _intrinsics(tmp_path, "w.json", '{"width": 1e400, "intrinsic_matrix": ' + f"{K}}}")
    line = _one_error_line(
        _run("register", depth, depth, "--features", "fpfh", "--intrinsics", wide)
    )
    assert str(wide) in line and "width" in line
    for value in ("nan", "inf"):
        _usage_error(
            _run("register", depth, depth, "--intrinsics", wide, "--depth-scale", value),
            "--depth-scale",
        )
    _usage_error(_run("register", depth, depth, "--seed", "99999999999999999999999"), "--seed")


def _subprocess_byoc(args, stdout):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    return subprocess.run(
        [sys.executable, "-m", "byoc_cli.cli.main", *map(str, args)],
        stdout=stdout,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        timeout=300,
    )


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_case7_stdout_full_or_closed_is_one_line(tmp_path):
    with open("/dev/full", "w") as full:
        done = _subprocess_byoc(["weights", "init", "-o", tmp_path / "w.safetensors"], full)
    assert done.returncode == 1, done.stderr
    assert done.stderr.strip().splitlines() == [done.stderr.strip()]
    assert "stdout" in done.stderr and "Traceback" not in done.stderr
    # the weights file the failed run wrote is not left behind
    assert not (tmp_path / "w.safetensors").exists()
    closed = subprocess.run(
        [sys.executable, "-m", "byoc_cli.cli.main", "weights", "info", tmp_path / "x"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        timeout=300,
    )
    assert closed.returncode == 1 and "Traceback" not in closed.stderr


@pytest.mark.skipif(os.name != "posix", reason="RLIMIT_FSIZE")
def test_case7_full_disk_on_output_is_one_line(pair, tmp_path):
    import resource
    import signal

    out = tmp_path / "T.txt"
    out.write_text("old T\n")

    def small_disk() -> None:  # writes past 100 bytes fail (EFBIG), as on a full disk
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (100, 100))

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    args = ["register", *pair, "--features", "fpfh", "-o", out]
    done = subprocess.run(
        [sys.executable, "-m", "byoc_cli.cli.main", *map(str, args)],
        capture_output=True,
        text=True,
        env=env,
        preexec_fn=small_disk,
        timeout=300,
    )
    assert done.returncode == 1, done.stderr
    assert done.stderr.strip().splitlines() == [f"byoc: error: {out}: cannot write: File too large"]
    assert out.read_text() == "old T\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["T.txt", "s.ply", "t.ply"]


# ---------------------------------------------------------------------------- 8-9 verdicts


def test_case8_unfittable_registration_is_exit_1(tmp_path, pair):
    t = np.linspace(0, 2, 500)
    line_src, line_tgt = tmp_path / "line.npy", tmp_path / "line2.npy"
    np.save(line_src, np.stack([t, 2 * t, np.ones_like(t)], 1))
    np.save(line_tgt, np.stack([t, 2 * t, np.ones_like(t)], 1) + 0.1)
    out = tmp_path / "T.txt"
    result = _register(line_src, line_tgt, "-o", out)
    line = _one_error_line(result)
    assert str(line_src) in line and "collinear" in line and not out.exists()
    assert "UserWarning" not in result.stderr
    result = _register(*pair, "--voxel-size", "10", "-o", out)
    line = _one_error_line(result)
    assert str(pair[0]) in line and "voxel size" in line and not out.exists()
    for option, value in (
        ("--min-confidence", "nan"),
        ("--voxel-size", "nan"),
        ("--scale", "nan"),
        ("--scale", "inf"),
    ):
        _usage_error(_register(*pair, option, value), option)


def test_case9_messages_name_the_file_and_the_real_problem(tmp_path, pair):
    big = tmp_path / "big.ply"
    big.write_text(
        "ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n1 2 3\n"
    )
    line = _one_error_line(_register(big, pair[1]))
    assert str(big) in line and "truncated" in line
    one = tmp_path / "one.npy"
    np.save(one, np.zeros((4, 3)))
    line = _one_error_line(_register(one, pair[1]))
    assert str(one) in line and "source:" not in line
    if Path("/proc").is_dir():
        line = _one_error_line(_register(*pair, "-o", "/proc/T.txt"))
        assert "/proc/T.txt" in line and "does not exist" not in line


def test_case9_weights_info_is_strict_json_and_checks_metrics(tmp_path):
    def infinite_voxel(meta, tensors):
        meta["voxel_size"] = float("inf")

    line = _one_error_line(
        _run("weights", "info", _weights_with(tmp_path, "inf.st", infinite_voxel))
    )
    assert "voxel_size" in line

    def text_metric(meta, tensors):
        meta["training"]["metrics"] = {"rot_acc_5": "excellent"}

    line = _one_error_line(_run("weights", "info", _weights_with(tmp_path, "str.st", text_metric)))
    assert "rot_acc_5" in line

    def nan_metric(meta, tensors):
        meta["training"]["metrics"] = {"loss": float("nan")}

    result = _run("weights", "info", "--json", _weights_with(tmp_path, "nan.st", nan_metric))
    assert result.exit_code == 0, result.output
    parsed = json.loads(result.stdout, parse_constant=lambda c: pytest.fail(f"not JSON: {c}"))
    assert parsed["training"]["metrics"] == {"loss": None}
