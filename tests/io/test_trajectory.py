"""TUM and .log trajectory files, quaternions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io.trajectory import (
    format_trajectory_log,
    format_tum_trajectory,
    matrix_to_quaternion,
    quaternion_to_matrix,
    read_trajectory,
    read_trajectory_log,
    read_tum_trajectory,
)


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        q = rng.normal(size=4)
        poses[k, :3, :3] = quaternion_to_matrix(q)
        poses[k, :3, 3] = rng.normal(size=3)
    return poses


def test_quaternion_by_hand():
    # 90 degrees about z: (0, 0, sin 45, cos 45); x -> y
    q = matrix_to_quaternion(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]))
    np.testing.assert_allclose(q, [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-15)
    np.testing.assert_allclose(matrix_to_quaternion(np.eye(3)), [0, 0, 0, 1])
    # 180 degrees about x: the scalar part is 0, the diagonal branch must be used
    np.testing.assert_allclose(
        matrix_to_quaternion(np.diag([1.0, -1, -1])), [1, 0, 0, 0], atol=1e-15
    )


@pytest.mark.parametrize("seed", range(5))
def test_quaternion_round_trip(seed):
    for pose in _random_poses(20, seed):
        R = pose[:3, :3]
        q = matrix_to_quaternion(R)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(quaternion_to_matrix(q), R, atol=1e-12)
        np.testing.assert_allclose(quaternion_to_matrix(-q), R, atol=1e-12)


def test_bad_quaternion_is_a_shape_error():
    with pytest.raises(ShapeError):
        quaternion_to_matrix(np.zeros(4))
    with pytest.raises(ShapeError):
        quaternion_to_matrix(np.array([0, 0, np.nan, 1.0]))


def test_tum_round_trip(tmp_path):
    poses = _random_poses(6)
    stamps = 1305031453.374112 + 0.0333 * np.arange(6)
    path = tmp_path / "traj.txt"
    path.write_text(format_tum_trajectory(stamps, poses))
    got_stamps, got_poses = read_tum_trajectory(path)
    np.testing.assert_array_equal(got_stamps, stamps)
    np.testing.assert_allclose(got_poses, poses, atol=1e-12)


def test_tum_lines_and_frame_numbers():
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    text = format_tum_trajectory([7], [pose])
    assert text.splitlines() == [
        "# timestamp tx ty tz qx qy qz qw",
        "7 1.0 2.0 3.0 0.0 0.0 0.0 1.0",
    ]


def test_tum_refuses_non_rigid_and_mismatched():
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ShapeError, match="orthonormal"):
        format_tum_trajectory([0], [bad])
    with pytest.raises(ShapeError, match="stamp"):
        format_tum_trajectory([0, 1], [np.eye(4)])


def test_tum_reader_names_the_bad_line(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("# c\n0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0\n")
    with pytest.raises(InputError, match="line 3"):
        read_tum_trajectory(path)


def test_log_is_read_back_by_open3d(tmp_path):
    o3d = pytest.importorskip("open3d")
    poses = _random_poses(3, seed=3)
    path = tmp_path / "trajectory.log"
    path.write_text(format_trajectory_log(poses))
    assert path.read_text().splitlines()[0] == "0 0 1"
    trajectory = o3d.io.read_pinhole_camera_trajectory(str(path))
    got = [np.linalg.inv(p.extrinsic) for p in trajectory.parameters]
    np.testing.assert_allclose(got, poses, atol=1e-9)


def test_log_with_ids():
    text = format_trajectory_log([np.eye(4), np.eye(4)], ids=[0, 2])
    assert [line for line in text.splitlines() if len(line.split()) == 3] == [
        "0 0 1",
        "2 2 3",
    ]
    with pytest.raises(ShapeError):
        format_trajectory_log([np.eye(4)], ids=[0, 1])


def test_log_round_trip_and_read_trajectory_by_suffix(tmp_path):
    poses = _random_poses(3, seed=4)
    path = tmp_path / "poses.log"
    path.write_text(format_trajectory_log(poses, ids=[0, 5, 7]) + "\n")
    ids, got = read_trajectory_log(path)
    assert ids.tolist() == [0, 5, 7]
    np.testing.assert_array_equal(got, poses)  # the shortest decimals read back exactly
    given = read_trajectory(path)
    assert given.format == "log" and given.keys.tolist() == [0, 5, 7]
    tum = tmp_path / "poses.txt"
    tum.write_text(format_tum_trajectory([0.5, 0.1, 0.2], poses))
    given = read_trajectory(tum)
    assert given.format == "tum" and given.keys.tolist() == [0.1, 0.2, 0.5]  # by stamp


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n", "line 1: record truncated"),
        ("0 0\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "line 1: expected a header"),
        ("0 0 1\n1 0 0 0\n0 1 0 x\n0 0 1 0\n0 0 0 1\n", "line 3: expected 4 numbers"),
        ("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0 9\n0 0 0 1\n", "line 4: expected 4 numbers"),
        ("0 0 1\n2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "line 1: the pose is not rigid"),
        ("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n", "line 5: the last row"),
        ("\n# nothing\n", "line 2: record truncated"),
        ("", "holds no pose"),
    ],
)
def test_log_reader_names_the_problem(tmp_path, text, needle):
    path = tmp_path / "bad.log"
    path.write_text(text)
    with pytest.raises(InputError, match=needle):
        read_trajectory(path)


def test_an_empty_tum_file_holds_no_pose(tmp_path):
    path = tmp_path / "empty.txt"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n")
    with pytest.raises(InputError, match="holds no pose"):
        read_trajectory(path)
