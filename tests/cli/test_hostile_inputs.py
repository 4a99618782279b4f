"""The numbered cases 2-9 of issue 21 ("hostile inputs, round two"), each as the user ran it:
through the CLI, checking the exit code, that stderr is one line naming the file (or the
option), that nothing blocks or grows without bound, and that a failed or killed run can be
run again with the same command. Case 1 is in test_no_file_lost.py.

Cases that would block (FIFOs) or eat the machine (``/dev/zero``, a sparse 5 GB file) on a
build without the fix run in a subprocess with a timeout and an address-space limit, so that
they fail instead of hanging or taking the machine down.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli
from byoc_cli.io import read_point_cloud, read_transform, write_ply

#: address space of a subprocess that reads hostile input (the issue's bar: no read of any
#: input grows past 2 GB): a read past it fails the test, not the machine
ADDRESS_SPACE = 2 << 30
TIMEOUT_S = 120


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


def _limit_address_space() -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


def _bounded(*args, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``byoc ARGS`` in a subprocess with a timeout and a 2 GB address space."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "byoc_cli.cli.main", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        preexec_fn=_limit_address_space,
        env=env,
        cwd=cwd,
    )


def _box(n: int = 3000, seed: int = 0) -> np.ndarray:
    """Points on the faces of a 3 x 2 x 1.6 m box, and a block inside (not symmetric)."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = np.sign(pts[np.arange(n), axis])
    block = rng.uniform(-0.3, 0.3, size=(n // 5, 3)) + np.array([0.5, 0.2, -0.5])
    return np.vstack([pts * np.array([1.5, 1.0, 0.8]), block])


@pytest.fixture
def pair(tmp_path: Path) -> tuple[Path, Path]:
    src, tgt = tmp_path / "s.ply", tmp_path / "t.ply"
    pts = _box()
    write_ply(src, pts)
    write_ply(tgt, pts + np.array([0.1, 0.0, 0.05]))
    return src, tgt


@pytest.fixture
def scans(tmp_path: Path) -> list[Path]:
    paths = []
    for k in range(3):
        paths.append(tmp_path / f"s{k}.ply")
        write_ply(paths[-1], _box() + np.array([0.03 * k, 0.02 * k, 0.0]))
    return paths


def _weights(path: Path, seed: int = 0) -> Path:
    from byoc_cli.pipeline.weights import init_weights, save_weights

    encoder, meta = init_weights("compact", seed)
    save_weights(path, encoder, meta)
    return path


def _train_args(shared_data: Path, out: Path, *extra) -> list:
    data = shared_data / "rgbd" / "tum_fr1_xyz"
    return [
        "train", "--rgbd-dir", data, "--variant", "byoc-geo", "--steps", "1", "--batch-size",
        "1", "--view-spacing", "2", "--val-every", "0", "--num-workers", "0", "--quiet",
        "--device", "cpu", "--out", out, *extra,
    ]  # fmt: skip


# ---------------------------------------------------------------------------- 2 the machine


def test_case2_num_workers_is_clamped_to_the_cores(shared_data, tmp_path, monkeypatch):
    """--num-workers 1000000 starts 2 workers per usable core (1 core here), with a warning."""
    import byoc_cli.training.loaders as loaders
    from byoc_cli import limits

    monkeypatch.setattr(limits, "usable_cores", lambda: 1)
    started = []
    real = loaders.DataLoader

    def recording(*args, num_workers=0, **kwargs):  # the real loader runs without workers
        started.append(num_workers)
        kwargs.update(persistent_workers=False, prefetch_factor=None, worker_init_fn=None)
        return real(*args, num_workers=0, **kwargs)

    monkeypatch.setattr(loaders, "DataLoader", recording)
    args = _train_args(shared_data, tmp_path / "run")
    args[args.index("--num-workers") + 1] = "1000000"
    args.remove("--quiet")  # -q keeps only errors on stderr: the warning is wanted here
    result = _run(*args)
    assert result.exit_code == 0, result.stderr
    assert started == [2], started
    assert "num_workers 1000000 is more than 2" in result.stderr, result.stderr


def test_case2_the_worker_bound_follows_the_affinity():
    from byoc_cli import limits
    from byoc_cli.training.loaders import loader_workers

    assert limits.usable_cores() == len(os.sched_getaffinity(0))
    bound = limits.max_workers()
    assert bound == limits.WORKERS_PER_CORE * limits.usable_cores()
    assert loader_workers(0) == 0 and loader_workers(bound) == bound
    with pytest.warns(UserWarning, match=f"starting {bound} data-loading workers"):
        assert loader_workers(10**6) == bound


# ---------------------------------------------------------------------------- 3 hostile files


def _fifo(path: Path) -> Path:
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs here")
    os.mkfifo(path)
    return path


def _hostile_args(role: str, path: Path, pair, shared_data: Path, out: Path) -> list:
    """A command that reads ``path`` in ``role``."""
    src, tgt = pair
    return {
        "cloud": ["register", path, tgt, "--features", "fpfh"],
        "weights": ["register", src, tgt, "--weights", path],
        "pairs": ["register-batch", path, "--features", "fpfh", "--out-dir", out],
        "config": ["train", "--config", path, "--rgbd-dir", shared_data, "--out", out],
        "init-weights": _train_args(shared_data, out, "--init-weights", path),
        "info": ["weights", "info", path],
    }[role]


ROLES = ["cloud", "weights", "pairs", "config", "init-weights", "info"]


@pytest.mark.parametrize("role", ROLES)
def test_case3_a_fifo_input_is_refused_without_blocking(pair, shared_data, tmp_path, role):
    fifo = _fifo(tmp_path / {"cloud": "f.ply", "pairs": "f.txt", "config": "f.toml"}.get(role, "f"))
    done = _bounded(*_hostile_args(role, fifo, pair, shared_data, tmp_path / "o"))
    assert done.returncode != 0
    assert f"{fifo}: is a FIFO, not a regular file" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.parametrize("role", ROLES[1:])
def test_case3_dev_zero_is_refused_before_a_byte_is_read(pair, shared_data, tmp_path, role):
    zero = Path("/dev/zero")
    if not zero.exists():
        pytest.skip("no /dev/zero here")
    done = _bounded(*_hostile_args(role, zero, pair, shared_data, tmp_path / "o"))
    assert done.returncode != 0
    assert f"{zero}: is a device, not a regular file" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_case3_a_sparse_5gb_weights_file_is_refused_from_its_size(pair, tmp_path):
    big = tmp_path / "big.safetensors"
    with open(big, "wb") as f:
        f.truncate(5 << 30)  # sparse: takes no disk
    for args in (["weights", "info", big], ["register", *pair, "--weights", big]):
        done = _bounded(*args)
        assert done.returncode == 1, done.stderr
        line = done.stderr.strip()
        assert line == f"byoc: error: {big}: is 5 GiB, larger than a weights file may be (512 MiB)"


def test_case3_a_header_claiming_100m_points_is_refused_before_reading(tmp_path):
    cloud = tmp_path / "big.ply"
    header = b"ply\nformat binary_little_endian 1.0\nelement vertex 100000000\n"
    header += b"property float x\nproperty float y\nproperty float z\nend_header\n"
    with open(cloud, "wb") as f:
        f.write(header)
        f.truncate(len(header) + 12 * 10**8)  # sparse, and large enough to hold them
    done = _bounded("features", cloud, "-o", tmp_path / "f.npz", "--features", "fpfh")
    assert done.returncode == 1, done.stderr
    assert "holds 100,000,000 points, more than byoc reads" in done.stderr, done.stderr
    with open(cloud, "r+b") as f:
        f.truncate(9 << 30)
    done = _bounded("features", cloud, "-o", tmp_path / "f.npz", "--features", "fpfh")
    assert "is 9 GiB, larger than a point-cloud file may be (8 GiB)" in done.stderr


# ---------------------------------------------------------------------------- 4-6 numbers


def _float_options():
    from byoc_cli.cli.main import _COMMANDS, LazyGroup

    group = LazyGroup()
    ctx = click.Context(cli)
    for name in _COMMANDS:
        command = group.get_command(ctx, name)
        commands = command.commands.values() if isinstance(command, click.Group) else [command]
        for sub in commands:
            for param in sub.params:
                if isinstance(param.type, click.FloatRange | type(click.FLOAT)):
                    yield f"{name} {sub.name}", param


def test_case4_every_float_option_is_finite_and_bounded_both_ways():
    found = list(_float_options())
    assert len(found) > 20
    for command, param in found:
        kind = param.type
        assert isinstance(kind, click.FloatRange), (command, param.name)
        assert kind.min is not None and kind.max is not None, (command, param.opts, kind)
        refused = ["nan", "inf", "1e300"] + (["1e-300"] if kind.min > 0 else [])
        for value in refused:
            with pytest.raises(click.BadParameter):
                kind.convert(value, param, None)


#: each command with the inputs it needs before the option is looked at
_BASE = {
    "odometry": ["odometry", "--rgbd-dir", "{data}"],
    "register-scans": ["register-scans", "{a}", "{b}", "--out", "{o}"],
    "make-fragments": ["make-fragments", "--rgbd-dir", "{data}", "--out", "{o}"],
    "register": ["register", "{a}", "{b}"],
    "eval-fmr": ["eval-fmr", "{data}"],
}


@pytest.mark.parametrize(
    "command,option,value",
    [
        ("odometry", "--icp-voxel", "1e-300"),
        ("register-scans", "--icp-voxel", "1e-300"),
        ("register-scans", "--merged-voxel", "1e-300"),
        ("make-fragments", "--tsdf-voxel", "1e-300"),
        ("register", "--scale", "1e300"),
        ("eval-fmr", "--tau1", "1e-300"),
    ],
)
def test_case4_tiny_and_huge_floats_are_usage_errors(pair, tmp_path, command, option, value):
    names = {"a": pair[0], "b": pair[1], "o": tmp_path / "o", "data": tmp_path}
    result = _run(*(a.format(**names) for a in _BASE[command]), option, value)
    _usage_error(result, option)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("lr", ["1e10", "1e30", "1e300"])
def test_case5_a_learning_rate_that_diverges_is_refused_before_anything_is_written(tmp_path, lr):
    out = tmp_path / "run"
    result = _run("train", "--rgbd-dir", tmp_path, "--out", out, "--lr", lr)
    _usage_error(result, "--lr")
    assert not out.exists()
    config = tmp_path / "c.toml"
    config.write_text(f"lr = {lr}\n")
    result = _run("train", "--rgbd-dir", tmp_path, "--out", out, "--config", config)
    assert (
        result.exit_code == 2 and str(config) in result.stderr and "lr must be in" in result.stderr
    )
    assert not out.exists()


def test_case5_a_run_that_diverges_ends_in_one_line_and_the_fixed_command_runs(
    shared_data, tmp_path, monkeypatch
):
    """A step that turns the weights into Inf (an infinite SGD step) ends the run with one
    line, before a checkpoint or weights are written; the same --out then trains."""
    import torch

    import byoc_cli.training.loop as loop

    out = tmp_path / "run"
    with monkeypatch.context() as patch:
        inf = float("inf")
        patch.setattr(
            loop, "build_optimizer", lambda m, c, **_: torch.optim.SGD(m.parameters(), inf)
        )
        result = _run(*_train_args(shared_data, out))
    assert result.exit_code == 1 and "Traceback" not in result.output, result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.startswith("byoc: error")]
    assert len(lines) == 1 and "training diverged at step 1" in lines[0], result.stderr
    assert "--lr" in lines[0]
    assert not (out / "weights.safetensors").exists()
    assert not list(out.rglob("*.pt"))
    result = _run(*_train_args(shared_data, out))
    assert result.exit_code == 0, result.stderr
    assert _run("weights", "info", out / "weights.safetensors").exit_code == 0


def test_case6_voxel_size_1e300_is_refused_by_train_and_weights_init(tmp_path):
    out = tmp_path / "w.safetensors"
    _usage_error(_run("weights", "init", "-o", out, "--voxel-size", "1e300"), "--voxel-size")
    _usage_error(
        _run("train", "--rgbd-dir", tmp_path, "--out", tmp_path / "r", "--voxel-size", "1e300"),
        "--voxel-size",
    )
    assert not out.exists() and not (tmp_path / "r").exists()


def _nan_weights(path: Path) -> Path:
    """A weights file that follows the spec but whose tensors are all NaN (a diverged run),
    written as a writer without the check would write it."""
    import torch
    from safetensors.torch import save

    from byoc_cli.io.jsonout import strict_dumps
    from byoc_cli.pipeline.weights import METADATA_KEY, init_weights, tensors_sha256

    encoder, meta = init_weights("compact", 0)
    tensors = {
        k: torch.full_like(v, float("nan")) if v.is_floating_point() else v.clone()
        for k, v in encoder.state_dict().items()
    }
    meta["tensors_sha256"] = tensors_sha256(tensors)
    path.write_bytes(save(tensors, metadata={METADATA_KEY: strict_dumps(meta, sort_keys=True)}))
    return path


def test_case6_weights_info_refuses_nan_tensors_and_nothing_writes_them(tmp_path):
    import torch

    from byoc_cli.errors import WeightsError
    from byoc_cli.pipeline.weights import init_weights, save_weights

    path = _nan_weights(tmp_path / "nan.safetensors")
    line = _one_error_line(_run("weights", "info", path))
    assert str(path) in line and "holds NaN or Inf" in line, line
    encoder, meta = init_weights("compact", 0)
    with torch.no_grad():
        next(encoder.parameters()).fill_(float("inf"))
    with pytest.raises(WeightsError, match="NaN or Inf"):
        save_weights(tmp_path / "out.safetensors", encoder, meta)
    with pytest.raises(WeightsError, match="voxel_size"):
        save_weights(tmp_path / "out.safetensors", *init_weights("compact", 0, 1e300))
    assert not (tmp_path / "out.safetensors").exists()


# ---------------------------------------------------------------------------- 7 stale results


def test_case7_a_rerun_with_fewer_scans_leaves_no_stale_pose(scans, tmp_path):
    out = tmp_path / "out"
    result = _run("register-scans", *scans, "--out", out, "--features", "fpfh")
    assert result.exit_code == 0, result.stderr
    assert (out / "poses" / "s2.txt").exists()
    result = _run("register-scans", *scans[:2], "--out", out, "--features", "fpfh")
    assert result.exit_code == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    listed = sorted(Path(s["pose"]).name for s in report["scans"] if s["pose"])
    assert sorted(p.name for p in (out / "poses").iterdir()) == listed == ["s0.txt", "s1.txt"]


# ---------------------------------------------------------------------------- 8 reruns


def test_case8_register_scans_killed_at_start_can_be_run_again(scans, tmp_path):
    out = tmp_path / "out"
    args = [sys.executable, "-m", "byoc_cli.cli.main", "register-scans", *scans]
    args += ["--out", out, "--features", "fpfh"]
    process = subprocess.Popen(list(map(str, args)), stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while not (out / "poses").is_dir() and time.monotonic() < deadline:
            time.sleep(0.02)
            if process.poll() is not None:
                pytest.fail("register-scans ended before it could be killed")
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    assert not (out / "report.json").exists()  # killed before it wrote anything
    result = _run("register-scans", *scans, "--out", out, "--features", "fpfh")
    assert result.exit_code == 0, result.stderr
    assert sorted(p.name for p in (out / "poses").iterdir()) == ["s0.txt", "s1.txt", "s2.txt"]


def test_case8_register_batch_refused_leaves_no_folder_and_no_summary(pair, tmp_path):
    src, tgt = pair
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{src} {tgt} {src}\n")  # its T file would replace its source
    line = _one_error_line(_run("register-batch", pairs, "--out-dir", tmp_path / "x" / "y" / "z"))
    assert "refusing to overwrite" in line
    assert not (tmp_path / "x").exists()
    pairs.write_text(f"{src} {tgt}\n")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not weights")
    out = tmp_path / "out"
    line = _one_error_line(_run("register-batch", pairs, "--out-dir", out, "--weights", bad))
    assert str(bad) in line
    assert not out.exists()
    out.mkdir()
    _one_error_line(_run("register-batch", pairs, "--out-dir", out, "--weights", bad))
    assert list(out.iterdir()) == []  # no empty summary.jsonl


def test_case8_make_fragments_removes_the_staging_folder_a_killed_run_left(tmp_path):
    from tests.pipeline import _synthetic as syn

    room = syn.write_sequence(tmp_path / "room", syn.orbit_poses(10))
    stale = tmp_path / ".frags.0123abcd.tmp"  # what a run killed while fusing leaves
    (stale / "room").mkdir(parents=True)
    (stale / "room" / "cloud_bin_0.ply").write_bytes(b"partial")
    fast = ["--frames-per-fragment", "5", "--tsdf-voxel", "0.02", "--sdf-trunc", "0.06"]
    result = _run("make-fragments", "--rgbd-dir", room, "--out", tmp_path / "frags", *fast)
    assert result.exit_code == 0, result.stderr
    assert not stale.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# ---------------------------------------------------------------------------- 9 names


def test_case9_a_legal_250_byte_output_name_works(pair, tmp_path):
    name = tmp_path / ("T" * 246 + ".txt")
    result = _run("register", *pair, "--features", "fpfh", "-o", name)
    assert result.exit_code == 0, result.stderr
    assert read_transform(name).shape == (4, 4)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_case9_an_output_name_ending_in_a_slash_is_refused(pair, tmp_path):
    for option in ("-o", "--aligned", "--json"):
        result = _run("register", *pair, "--features", "fpfh", option, f"{tmp_path}/newdir/")
        _usage_error(result, option)
    assert not (tmp_path / "newdir").exists()


def test_case9_dash_is_stdout_for_every_output(pair, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = _run("features", pair[0], "--features", "fpfh", "-o", "-")
    assert result.exit_code == 0, result.stderr
    import io

    with np.load(io.BytesIO(result.stdout_bytes)) as npz:
        assert npz["features"].shape[1] == 33
    result = _run("weights", "init", "-o", "-")
    assert result.exit_code == 0, result.stderr
    (tmp_path / "w.safetensors").write_bytes(result.stdout_bytes)
    assert _run("weights", "info", tmp_path / "w.safetensors").exit_code == 0
    result = _run("register", *pair, "--features", "fpfh", "-o", "T.txt", "--aligned", "-")
    assert result.exit_code == 0, result.stderr
    (tmp_path / "aligned.ply").write_bytes(result.stdout_bytes)
    assert read_point_cloud(tmp_path / "aligned.ply").points.shape == (3600, 3)
    _usage_error(_run("features", pair[0], "--features", "fpfh", "--npy", "-o", "-"), "-o")
    assert not (tmp_path / "-").exists()


def test_case9_options_that_are_not_used_are_said_on_stderr(pair, tmp_path):
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not weights")
    result = _run("register", *pair, "--features", "fpfh", "--weights", bad, "-o", tmp_path / "T")
    assert result.exit_code == 0, result.stderr
    assert f"--weights {bad} is not used: --features fpfh" in result.stderr
    intrinsics = tmp_path / "K.json"
    result = _run("register", *pair, "--features", "fpfh", "--intrinsics", intrinsics)
    assert result.exit_code == 0, result.stderr
    assert f"--intrinsics {intrinsics} is not used: no input is a depth image" in result.stderr


# ---------------------------------------------------------------------------- past the list


def test_deeply_nested_json_and_toml_are_one_line_errors(pair, tmp_path):
    """A header, metadata, intrinsics or config nested 200,000 levels deep used to end in a
    RecursionError traceback."""
    import struct

    deep = "[" * 200_000 + "]" * 200_000
    header = tmp_path / "header.safetensors"
    header.write_bytes(struct.pack("<Q", len(deep)) + deep.encode())
    meta = json.dumps({"__metadata__": {"byoc": deep}}).encode()
    metadata = tmp_path / "meta.safetensors"
    metadata.write_bytes(struct.pack("<Q", len(meta)) + meta)
    for path, phrase in ((header, "header is not JSON"), (metadata, "metadata is not valid")):
        line = _one_error_line(_run("weights", "info", path))
        assert str(path) in line and phrase in line, line
    config = tmp_path / "deep.toml"
    config.write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    line = _one_error_line(_run("train", "--config", config, "--rgbd-dir", tmp_path))
    assert str(config) in line and "nested too deeply" in line, line
    intrinsics = tmp_path / "K.json"
    intrinsics.write_text('{"intrinsic_matrix": ' + deep + "}")
    depth = tmp_path / "d.png"
    from PIL import Image

    Image.fromarray(np.full((4, 4), 1000, np.uint16)).save(depth)
    result = _run("register", depth, depth, "--features", "fpfh", "--intrinsics", intrinsics)
    line = _one_error_line(result)
    assert str(intrinsics) in line and "nested too deeply" in line, line


def test_a_cloud_too_wide_for_its_voxels_names_the_file(pair):
    """--scale 1e6 makes a 3 m box 3000 km wide: at a fixed voxel of centimetres, more voxels
    than the keys hold (the auto voxel grows with the cloud and registers it)."""
    for features, voxel in (("byoc", "0.025"), ("fpfh", "0.05")):
        args = ("--features", features, "--scale", "1e6", "--voxel-size", voxel)
        line = _one_error_line(_run("register", *pair, *args))
        assert str(pair[0]) in line and "voxel size is too small for this cloud" in line, line


def test_a_first_frame_without_points_names_its_depth_file(shared_data):
    data = shared_data / "rgbd" / "tum_fr1_xyz"
    result = _run("odometry", "--rgbd-dir", data, "--features", "fpfh", "--max-depth", "1e-4")
    line = _one_error_line(result)
    assert str(data / "depth") in line and "fewer than 10 points within 0.0001 m" in line, line


def test_a_truncation_of_many_tsdf_voxels_is_a_usage_error(tmp_path):
    """--tsdf-voxel 0.002 --sdf-trunc 1 made open3d allocate blocks until malloc failed (a
    traceback after 4.6 GB)."""
    args = ["make-fragments", "--rgbd-dir", tmp_path, "--out", tmp_path / "o"]
    _usage_error(_run(*args, "--tsdf-voxel", "0.002", "--sdf-trunc", "1"), "--sdf-trunc")
    _usage_error(_run(*args, "--tsdf-voxel", "0.001"), "--tsdf-voxel")
    assert not (tmp_path / "o").exists()


def test_a_gt_log_of_millions_of_short_lines_is_read_a_record_at_a_time(shared_data, tmp_path):
    """A 64 MiB gt.log (the cap) of 2 million repeated short records grew to 2.4 GB before
    its second record was refused; records are now parsed one at a time."""
    import shutil

    bench = tmp_path / "bench"
    shutil.copytree(shared_data / "3dmatch" / "sample" / "3DMatch", bench)
    gt_log = bench / "7-scenes-redkitchen-evaluation" / "gt.log"
    record = b"0 4 5\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"
    gt_log.write_bytes(record * ((64 << 20) // len(record)))
    done = _bounded("eval-fmr", bench, "--method", "identity", "--quiet")
    assert done.returncode == 1, done.stderr
    assert f"{gt_log}: line 6: pair 0 4 repeats the record of line 1" in done.stderr
