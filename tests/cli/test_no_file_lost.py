"""Every command, run in failing ways on one folder of inputs and earlier outputs: hashing
every file before and after shows that no failed run changes, removes or adds a file."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from byoc_cli.cli.main import cli
from byoc_cli.io import write_ply, write_transform


def _box(n: int = 1200, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = np.sign(pts[np.arange(n), axis])
    return pts * np.array([1.5, 1.0, 0.8])


def _gt_log(path: Path, pairs: list[tuple[int, int]], total: int) -> None:
    rows = [f"{i} {j} {total}\n" + "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n" for i, j in pairs]
    path.write_text("".join(rows))


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """Inputs of every command and the outputs of earlier runs, side by side."""
    root = tmp_path_factory.mktemp("work")
    pts = _box()
    write_ply(root / "s.ply", pts)
    write_ply(root / "t.ply", pts + np.array([0.1, 0.0, 0.05]))
    t = np.linspace(0, 2, 300)
    np.save(root / "line.npy", np.stack([t, 2 * t, np.ones_like(t)], 1))
    (root / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 5\nend_header\n")
    Image.fromarray(np.full((24, 32), 1000, dtype=np.uint16)).save(root / "depth.png")
    (root / "intrinsics.txt").write_text("1e-7 0 16\n0 1e-7 12\n0 0 1\n")
    assert (
        CliRunner().invoke(cli, ["weights", "init", "-o", str(root / "w.safetensors")]).exit_code
        == 0
    )
    (root / "bad.safetensors").write_bytes(b"\x04\0\0\0\0\0\0\0abcd")
    # earlier outputs the user keeps
    write_transform(root / "T.txt", np.eye(4))
    (root / "report.json").write_text('{"earlier": "report"}\n')
    write_ply(root / "aligned.ply", pts[:10])
    (root / "plot.png").write_bytes(b"an earlier plot")
    # a 3DMatch-layout benchmark with a broken gt.log, and prepared pairs
    scene = root / "bench" / "kitchen"
    scene.mkdir(parents=True)
    for k in range(2):
        write_ply(scene / f"cloud_bin_{k}.ply", pts + 0.01 * k)
    (root / "bench" / "kitchen-evaluation").mkdir()
    (root / "bench" / "kitchen-evaluation" / "gt.log").write_text("0 1 2\n1 0 0\n")
    pair = root / "pairs" / "0000"
    pair.mkdir(parents=True)
    write_ply(pair / "source.ply", pts)
    write_ply(pair / "target.ply", pts + 0.02)
    write_transform(pair / "T_gt.txt", np.eye(4))
    # a folder with the user's own training results (no byoc config.json)
    mine = root / "mine"
    (mine / "checkpoints").mkdir(parents=True)
    (mine / "weights.safetensors").write_bytes(b"my weights")
    (mine / "checkpoints" / "step-00000005.pt").write_bytes(b"my checkpoint")
    return root


def _snapshot(root: Path) -> dict[str, str]:
    return {
        str(path.relative_to(root)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
        if path.is_file()
    }


def _fail_rename_of(name: str):
    """``os.replace`` that fails when it would put a new ``name`` in place."""
    real = os.replace

    def replace(src, dst, *args, **kwargs):
        if Path(dst).name == name and Path(src).name.endswith(".tmp"):
            raise OSError(28, "No space left on device")
        return real(src, dst, *args, **kwargs)

    return replace


REG = ["register", "s.ply", "t.ply", "--features", "fpfh"]
SCANS = ["register-scans", "s.ply", "t.ply", "--out", "scans", "--features", "fpfh"]
ODOMETRY = ["odometry", "--features", "fpfh", "--rgbd-dir"]
OUTS = ["-o", "T.txt", "--json", "report.json", "--aligned", "aligned.ply"]
EVAL_PAIRS = ["eval-pairs", "--pairs-dir", "pairs", "--method", "identity", "--quiet"]
FAILING_RUNS = {
    "register over its source": [*REG, "-o", "s.ply"],
    "register aligned over its target": [*REG, "--aligned", "t.ply", "-o", "T.txt"],
    "register into a missing folder": [*REG, "--json", "report.json", "-o", "no/T.txt"],
    "register into a folder": [*REG, "--json", "report.json", "-o", "mine"],
    "register a bad cloud": ["register", "s.ply", "bad.ply", "--features", "fpfh", *OUTS],
    "register a collinear cloud": ["register", "line.npy", "s.ply", "--features", "fpfh", *OUTS],
    "register bad intrinsics": [
        *["register", "depth.png", "depth.png", "--intrinsics", "intrinsics.txt", *OUTS]
    ],
    "register bad weights": [*REG[:3], "--weights", "bad.safetensors", *OUTS],
    "register nan option": [*REG, "--voxel-size", "nan", *OUTS],
    "register commit fails": [*REG, *OUTS],
    "weights info bad": ["weights", "info", "bad.safetensors"],
    "weights init unknown arch": ["weights", "init", "--arch", "big", "-o", "w.safetensors"],
    "weights init over a folder": ["weights", "init", "-o", "mine"],
    "weights init commit fails": ["weights", "init", "-o", "w.safetensors"],
    "train into the user's folder": [
        *["train", "--rgbd-dir", "pairs", "--out", "mine", "--steps", "1", "--device", "cpu"]
    ],
    "train resume of a non-run": ["train", "--resume", "mine"],
    "eval-fmr broken gt.log": [
        *["eval-fmr", "bench", "--method", "identity", "--json", "report.json", "--plot"],
        "plot.png",
    ],
    "eval-fmr over a fragment": [
        *["eval-fmr", "bench", "--method", "identity", "--json"],
        "bench/kitchen/cloud_bin_0.ply",
    ],
    "eval-pairs into a missing folder": [
        *EVAL_PAIRS,
        "--json",
        "report.json",
        "--plot",
        "no/p.png",
    ],
    "eval-pairs over its input": [*EVAL_PAIRS, "--json", "pairs/0000/T_gt.txt"],
    "eval-pairs commit fails": [*EVAL_PAIRS, "--json", "report.json", "--plot", "plot.png"],
    "register-scans over its input": [*SCANS, "--merged", "s.ply"],
    "register-scans a bad cloud": ["register-scans", "s.ply", "bad.ply", "--out", "scans"],
    "register-scans into the user's folder": [*SCANS[:3], "--out", "mine"],
    "register-scans commit fails": [*SCANS, "--merged", "aligned.ply"],
    "odometry of a folder without a sequence": [*ODOMETRY, "pairs", "-o", "T.txt"],
    "odometry into a folder": [*ODOMETRY, "pairs", "-o", "mine", "--json", "report.json"],
}
#: runs that succeed up to the end and then fail to put this file in place
COMMIT_FAILS = {
    "register-scans commit fails": "aligned.ply",
    "register commit fails": "T.txt",
    "weights init commit fails": "w.safetensors",
    "eval-pairs commit fails": "report.json",
}


@pytest.mark.parametrize("case", sorted(FAILING_RUNS))
def test_a_failed_run_changes_no_file(work, case, monkeypatch):
    monkeypatch.chdir(work)
    before = _snapshot(work)
    if case in COMMIT_FAILS:
        monkeypatch.setattr(os, "replace", _fail_rename_of(COMMIT_FAILS[case]))
    result = CliRunner().invoke(cli, FAILING_RUNS[case])
    assert result.exit_code in (1, 2), (result.exit_code, result.output)
    assert "Traceback" not in result.output
    errors = [
        line for line in result.stderr.splitlines() if line.startswith(("byoc: error", "Error"))
    ]
    assert len(errors) == 1, result.stderr
    after = _snapshot(work)
    assert not (work / "scans").exists()  # register-scans removes the folders it made
    changed = sorted(k for k in before if before[k] != after.get(k))
    added = sorted(set(after) - set(before))
    assert not changed and not added, (changed, added)
    assert json.loads((work / "report.json").read_text()) == {"earlier": "report"}


def test_every_command_is_exercised():
    commands = {run[0] for run in FAILING_RUNS.values()}
    assert commands == {
        *("register", "weights", "train", "eval-fmr", "eval-pairs"),
        *("register-scans", "odometry"),
    }
    assert {run[1] for run in FAILING_RUNS.values() if run[0] == "weights"} == {"info", "init"}


@pytest.mark.parametrize("shard", ["1/2", "2/2", None])
@pytest.mark.parametrize("overwrite", [False, True])
def test_a_shard_never_writes_over_an_input_of_another_shard(work, shard, overwrite, monkeypatch):
    """Line 2 names ``s.ply`` (line 1's source) as its T file: every shard refuses the list,
    with or without --overwrite, and no file changes (it used to replace s.ply in shard 2/2,
    and count it as "skipped (T file exists)" without --overwrite)."""
    monkeypatch.chdir(work)
    listing = work / "pairs.txt"
    listing.write_text("s.ply t.ply T1.txt\naligned.ply t.ply s.ply\n")
    before = _snapshot(work)
    args = ["register-batch", "pairs.txt", "--features", "fpfh"]
    args += ["--shard", shard] if shard else []
    args += ["--overwrite"] if overwrite else []
    try:
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 1, (result.exit_code, result.output)
        errors = [line for line in result.stderr.splitlines() if line.startswith("byoc: error")]
        assert len(errors) == 1 and "s.ply" in errors[0], result.stderr
        assert "input" in errors[0]
        assert _snapshot(work) == before
    finally:
        listing.unlink()
