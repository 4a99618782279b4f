"""`byoc odometry --init-poses`: a real TUM window tracked from its perturbed ground truth
(TUM, matched by timestamp; .log, by frame number); trajectories that match no frame or are
malformed are one line, exit 1, before any work."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli
from byoc_cli.io.rgbd import discover_sequences
from byoc_cli.io.trajectory import format_trajectory_log, format_tum_trajectory
from tests.pipeline._rooms import perturbed, turn_z

FAST = ["--features", "fpfh", "-q"]


def _invoke(args: list) -> object:
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def xyz(shared_data):
    """The 10 frames of tum_fr1_xyz, their stamps and their ground truth perturbed by 2 deg
    and 2 cm each, in a world of its own."""
    root = shared_data / "rgbd" / "tum_fr1_xyz"
    sequence = discover_sequences(root, require_poses=True)[0]
    rng = np.random.default_rng(0)
    world = turn_z(30.0, (3.0, -1.0, 0.5))
    given = [world @ perturbed(sequence.pose(k), 2.0, 0.02, rng) for k in range(10)]
    stamps = [frame.timestamp for frame in sequence.frames]
    return root, stamps, given


def _run(root, init, tmp_path):
    out = tmp_path / "traj.txt"
    result = _invoke(["odometry", "--rgbd-dir", root, "-o", out, "--json", "-", "--eval",
                      "--init-poses", init, *FAST])  # fmt: skip
    return result, out


@pytest.mark.parametrize("fmt", ["tum", "log"])
def test_tracking_starts_from_the_given_motion(xyz, tmp_path, fmt):
    root, stamps, given = xyz
    init = tmp_path / f"init.{'txt' if fmt == 'tum' else 'log'}"
    if fmt == "tum":  # 5 ms off the frames' stamps: matched to the nearest within 20 ms
        init.write_text(format_tum_trajectory(np.asarray(stamps) + 0.005, given))
    else:  # .log: by frame number (TUM: the position in depth.txt)
        init.write_text(format_trajectory_log(given))
    result, out = _run(root, init, tmp_path)
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["stats"]["start_init"] == 9 and report["stats"]["start_velocity"] == 0
    assert report["init_poses"]["format"] == fmt and report["init_poses"]["frames_matched"] == 10
    ate = report["evaluation"]["ate_m"]["rmse"]
    print(f"fr1_xyz from its ground truth 2 deg / 2 cm off: ATE {ate:.4f} m")
    assert ate < 0.01  # measured 0.0042 m, as from the constant velocity
    assert out.exists()


def test_a_trajectory_of_other_times_is_one_line_exit_1(xyz, tmp_path):
    root, stamps, given = xyz
    init = tmp_path / "late.txt"
    init.write_text(format_tum_trajectory(np.asarray(stamps) + 100.0, given))
    result, out = _run(root, init, tmp_path)
    assert result.exit_code == 1
    assert result.stderr.startswith(f"byoc: error: {init}: gives a pose to 0 of the 10 frames")
    assert "within 0.02 s" in result.stderr and len(result.stderr.splitlines()) == 1
    assert not out.exists()


def test_a_malformed_trajectory_is_one_line_exit_1(xyz, tmp_path):
    root, _, _ = xyz
    init = tmp_path / "bad.log"
    init.write_text("0 0 1\n1 0 0 0\n0 1 0 0\n")
    result, out = _run(root, init, tmp_path)
    assert result.exit_code == 1
    problem = "line 1: record truncated (a line 'i i n' and 4 rows)"
    assert result.stderr == f"byoc: error: {init}: {problem}\n"
    assert not out.exists()
