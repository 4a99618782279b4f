"""Odometry from a given trajectory (``given``): its motion is where each frame's ICP starts,
the constant velocity where it does not fit."""

from __future__ import annotations

import numpy as np
import pytest

from byoc_cli.evaluation.trajectory import absolute_trajectory_error
from byoc_cli.io.rgbd import discover_sequences
from byoc_cli.pipeline.odometry import OdometryConfig, estimate_trajectory
from tests.pipeline import _synthetic as syn
from tests.pipeline._rooms import perturbed, turn_z

SYN_VOXEL = 0.03


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    root = syn.write_sequence(tmp_path_factory.mktemp("odo") / "room", syn.orbit_poses(15))
    return discover_sequences(root)[0]


class _Jump:
    """Frames 0, 1, 2, then 12, 13, 14 of the orbit: a 30-degree jump."""

    def __init__(self, orbit):
        self.orbit, self.order = orbit, (0, 1, 2, 12, 13, 14)
        self.frames = [orbit.frames[k] for k in self.order]
        self.K = orbit.K

    def read_depth(self, i):
        return self.orbit.read_depth(self.order[i])


def test_the_given_motion_carries_tracking_over_a_jump(orbit):
    jump = _Jump(orbit)
    gt = np.stack([orbit.pose(k) for k in jump.order])
    truth = np.linalg.inv(gt[0]) @ gt
    config = OdometryConfig(voxel_size=SYN_VOXEL)
    plain = estimate_trajectory(jump, config)
    # the setting: from the constant velocity, ICP settles 30 deg later on a wrong pose that
    # fits (measured ATE 0.080 m)
    assert absolute_trajectory_error(plain.poses, truth).rmse > 0.03
    rng = np.random.default_rng(0)
    world = np.eye(4)
    world[:3, 3] = [5.0, -2.0, 0.3]  # the given trajectory's world is its own
    given = [world @ perturbed(pose, 2.0, 0.02, rng) for pose in gt]
    result = estimate_trajectory(jump, config, given=given)
    assert result.stats["start_init"] == 5 and result.stats["start_velocity"] == 0
    ate = absolute_trajectory_error(result.poses, truth).rmse
    assert ate < 0.005, ate  # measured 0.002 m; the given poses are 2 deg and 2 cm off


def test_a_wrong_motion_falls_back_to_the_constant_velocity(orbit):
    gt = np.stack([orbit.pose(k) for k in range(6)])
    # a quarter turn a frame about the optical axis that the camera never made (a given
    # motion 45 deg off still ends where ICP fits, wrongly: fitness 0.68, ATE 0.17 m)
    wrong = [pose @ turn_z(90.0 * k) for k, pose in enumerate(gt)]
    config = OdometryConfig(voxel_size=SYN_VOXEL, max_frames=6)
    result = estimate_trajectory(orbit, config, given=wrong + [None] * 9)
    assert result.stats["start_init"] == 0 and result.stats["start_velocity"] == 5
    ate = absolute_trajectory_error(result.poses, np.linalg.inv(gt[0]) @ gt)
    assert ate.rmse < 0.01


def test_given_is_one_entry_per_frame(orbit):
    with pytest.raises(ValueError, match="15 frames"):
        estimate_trajectory(orbit, OdometryConfig(voxel_size=SYN_VOXEL), given=[np.eye(4)])
