"""`byoc make-fragments` end to end on a synthetic posed sequence; exit codes of bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli
from byoc_cli.io import read_gt_info, read_gt_log
from tests.pipeline import _synthetic as syn

FAST = ["--frames-per-fragment", "5", "--tsdf-voxel", "0.02", "--sdf-trunc", "0.06"]


def _invoke(args: list) -> object:
    return CliRunner().invoke(cli, [str(a) for a in args])


def _one_error_line(result, *needles: str) -> None:
    lines = [ln for ln in result.stderr.splitlines() if ln.startswith("byoc: error:")]
    assert len(lines) == 1, result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return syn.write_sequence(tmp_path_factory.mktemp("cli") / "room", syn.orbit_poses(15))


def test_make_fragments_writes_the_benchmark(room, tmp_path):
    out = tmp_path / "bench"
    result = _invoke(["make-fragments", "--rgbd-dir", room, "--out", out, *FAST])
    assert result.exit_code == 0, result.output
    # the sequence seq-01 lies below --rgbd-dir: the scene is named after both
    scene = "room-seq-01"
    assert sorted(p.name for p in (out / scene).iterdir()) == [
        f"cloud_bin_{k}.ply" for k in range(3)
    ]
    records = read_gt_log(out / f"{scene}-evaluation" / "gt.log")
    infos = read_gt_info(out / f"{scene}-evaluation" / "gt.info")
    assert [(r.i, r.j) for r in records] == [(r.i, r.j) for r in infos] and records
    stdout = result.stdout.strip().splitlines()
    assert len(stdout) == 1 and f"3 fragments, {len(records)} pairs" in stdout[0]
    progress = [ln for ln in result.stderr.splitlines() if ln.startswith("byoc: fragment")]
    assert len(progress) == 3 and "frames 10-14" in progress[2]


def test_scene_and_stride_flags(room, tmp_path):
    out = tmp_path / "bench"
    args = ["make-fragments", "--rgbd-dir", room / "seq-01", "--out", out, "--scene", "kitchen"]
    result = _invoke(
        [*args, *FAST, "--stride", "2", "--intrinsics", room / "camera-intrinsics.txt"]
    )
    assert result.exit_code == 0, result.output
    assert len(list((out / "kitchen").glob("cloud_bin_*.ply"))) == 6  # starts 0, 2, ..., 10


def test_nonempty_out_is_refused(room, tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "x").write_text("x")
    result = _invoke(["make-fragments", "--rgbd-dir", room, "--out", out, *FAST])
    assert result.exit_code == 1
    _one_error_line(result, str(out), "not empty")
    assert result.stdout == ""


def test_sequence_without_poses_is_refused(tmp_path):
    root = syn.write_sequence(tmp_path / "unposed", syn.orbit_poses(6), with_poses=False)
    result = _invoke(["make-fragments", "--rgbd-dir", root, "--out", tmp_path / "o", *FAST])
    assert result.exit_code == 1
    _one_error_line(result, str(root), "poses")
    assert not (tmp_path / "o").exists()


def test_missing_folder_short_sequence_and_corrupt_frame(room, tmp_path):
    result = _invoke(["make-fragments", "--rgbd-dir", tmp_path / "nope", "--out", tmp_path / "o"])
    assert result.exit_code == 1
    _one_error_line(result, "nope", "does not exist")
    result = _invoke(["make-fragments", "--rgbd-dir", room, "--out", tmp_path / "o"])  # N = 50
    assert result.exit_code == 1
    _one_error_line(result, "fewer than one fragment")
    broken = syn.write_sequence(tmp_path / "broken", syn.orbit_poses(10))
    (broken / "seq-01" / "frame-000007.depth.png").write_bytes(b"garbage")
    result = _invoke(["make-fragments", "--rgbd-dir", broken, "--out", tmp_path / "o", *FAST])
    assert result.exit_code == 1
    _one_error_line(result, "frame-000007.depth.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken"]  # nothing half-written


@pytest.mark.parametrize(
    ("extra", "flag"),
    [
        (["--scene", "a/b"], "--scene"),
        (["--sdf-trunc", "0.01"], "--sdf-trunc"),
        (["--min-overlap", "1"], "--min-overlap"),
        (["--frames-per-fragment", "0"], "--frames-per-fragment"),
    ],
)
def test_usage_errors_exit_2_naming_the_flag(room, tmp_path, extra, flag):
    base = ["make-fragments", "--rgbd-dir", room, "--out", tmp_path / "o", *FAST]
    result = _invoke([*base, *extra])
    assert result.exit_code == 2 and flag in result.stderr, result.stderr
    assert not (tmp_path / "o").exists()


def test_eval_fmr_reads_the_made_benchmark(room, tmp_path):
    out = tmp_path / "bench"
    assert _invoke(["make-fragments", "--rgbd-dir", room, "--out", out, *FAST]).exit_code == 0
    result = _invoke(["eval-fmr", out, "--method", "identity", "--quiet", "--json", "-"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert (
        report["num_pairs"]
        == report["num_pairs_with_info"]
        == len(read_gt_log(out / "room-seq-01-evaluation" / "gt.log"))
    )
