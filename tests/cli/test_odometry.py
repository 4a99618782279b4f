"""`byoc odometry` end to end: a synthetic posed sequence, a real TUM window, bad input."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from byoc_cli.evaluation.trajectory import absolute_trajectory_error
from byoc_cli.io.rgbd import discover_sequences
from byoc_cli.io.trajectory import read_tum_trajectory
from tests.cli._run import invoke as _invoke
from tests.cli._run import one_error_line as _one_error_line
from tests.pipeline import _synthetic as syn

FAST = ["--features", "fpfh", "--icp-voxel", "0.03"]


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    return syn.write_sequence(tmp_path_factory.mktemp("odo") / "room", syn.orbit_poses(10))


def test_odometry_writes_a_tum_trajectory_with_frame_numbers(orbit, tmp_path):
    out = tmp_path / "traj.txt"
    result = _invoke(["odometry", "--rgbd-dir", orbit, "-o", out, "--eval", "--json", "-", *FAST])
    assert result.exit_code == 0, result.output
    stamps, poses = read_tum_trajectory(out)
    np.testing.assert_array_equal(stamps, np.arange(10))  # no timestamps: the frame numbers
    sequence = discover_sequences(orbit)[0]
    gt = np.stack([sequence.pose(i) for i in range(10)])
    assert absolute_trajectory_error(poses, gt).rmse < 0.01
    report = json.loads(result.stdout)
    assert report["num_frames"] == 10 and report["lost_frames"] == []
    evaluation = report["evaluation"]
    assert evaluation["ate_m"]["rmse"] < 0.01
    assert set(evaluation["rpe"]) == {"per_frame"}  # no timestamps, no per-second RPE
    assert "ATE RMSE (m)" in result.stderr


def test_trajectory_to_stdout(orbit):
    result = _invoke(["odometry", "--rgbd-dir", orbit, "--max-frames", "3", *FAST])
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines[0].startswith("# timestamp") and len(lines) == 4


def test_real_window_with_eval(shared_data, tmp_path):
    out = tmp_path / "traj.txt"
    report_path = tmp_path / "odo.json"
    seq = shared_data / "rgbd" / "tum_fr1_desk_full"
    result = _invoke(["odometry", "--rgbd-dir", seq, "--max-frames", "30", "--features", "fpfh",
                      "--eval", "-o", out, "--json", report_path])  # fmt: skip
    assert result.exit_code == 0, result.output
    stamps, _ = read_tum_trajectory(out)
    assert stamps[0] == pytest.approx(1305031453.374112)  # TUM timestamps kept
    evaluation = json.loads(report_path.read_text())["evaluation"]
    print(f"odometry CLI, 30 frames of fr1_desk: {evaluation}")
    assert evaluation["ate_m"]["rmse"] < 0.04  # measured 0.022 m
    assert evaluation["rpe"]["per_second"]["num_pairs"] > 0


# ------------------------------------------------------------------ bad input


def test_eval_without_ground_truth_is_one_line_exit_1(orbit, tmp_path):
    unposed = tmp_path / "unposed"
    shutil.copytree(orbit, unposed)
    for pose in unposed.rglob("*.pose.txt"):
        pose.unlink()
    out = tmp_path / "traj.txt"
    result = _invoke(["odometry", "--rgbd-dir", unposed, "-o", out, "--eval", *FAST])
    assert result.exit_code == 1
    _one_error_line(result, "--eval needs ground-truth poses")
    assert not out.exists()


def test_a_corrupt_depth_frame_is_one_line_exit_1(orbit, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(orbit, broken)
    frame = broken / "seq-01" / "frame-000004.depth.png"
    frame.write_bytes(frame.read_bytes()[:50])
    out = tmp_path / "traj.txt"
    json_path = tmp_path / "odo.json"
    result = _invoke(["odometry", "--rgbd-dir", broken, "-o", out, "--json", json_path, *FAST])
    assert result.exit_code == 1
    _one_error_line(result, "frame-000004.depth.png")
    assert not out.exists() and not json_path.exists()


def test_missing_folder_and_usage_errors(orbit, tmp_path, monkeypatch):
    missing = _invoke(["odometry", "--rgbd-dir", tmp_path / "nope", "-o", tmp_path / "t.txt",
                       *FAST])  # fmt: skip
    assert missing.exit_code == 1
    _one_error_line(missing, "nope")
    both = _invoke(["odometry", "--rgbd-dir", orbit, "-o", "-", "--json", "-", *FAST])
    assert both.exit_code == 2
    # an install without shipped weights: byoc features need --weights
    from byoc_cli.pipeline import default_weights

    monkeypatch.setattr(default_weights, "DEFAULT_WEIGHTS", tmp_path / "none.safetensors")
    weights = _invoke(["odometry", "--rgbd-dir", orbit, "-o", tmp_path / "t.txt"])
    assert weights.exit_code == 2 and "--weights" in weights.output
    assert not (tmp_path / "t.txt").exists()
