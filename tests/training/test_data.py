import math

import pytest
import torch

from byoc_cli.geometry import apply_transform, invert_transform, make_transform
from byoc_cli.geometry.transforms import axis_angle_to_matrix
from byoc_cli.training.data import ResumableSampler, relative_pose


def _pose(axis_angle, t):
    return make_transform(
        axis_angle_to_matrix(torch.tensor(axis_angle, dtype=torch.float64)),
        torch.tensor(t, dtype=torch.float64),
    )


def test_relative_pose_direction_maps_frame_j_into_frame_i():
    # T_world_cam of two cameras; one world point seen by both
    T_w_i = _pose([0.1, -0.2, 0.3], [0.5, 0.1, -0.2])
    T_w_j = _pose([-0.3, 0.4, 0.1], [1.0, -0.5, 0.3])
    x_world = torch.tensor([[0.3, -0.7, 2.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    x_i = apply_transform(invert_transform(T_w_i), x_world)
    x_j = apply_transform(invert_transform(T_w_j), x_world)
    T_i_j = relative_pose(T_w_i, T_w_j)
    torch.testing.assert_close(apply_transform(T_i_j, x_j), x_i)
    # the other direction is the inverse
    torch.testing.assert_close(apply_transform(relative_pose(T_w_j, T_w_i), x_i), x_j)


def test_relative_pose_accepts_numpy():
    T = _pose([0.0, 0.0, math.pi / 2], [1.0, 2.0, 3.0])
    torch.testing.assert_close(
        relative_pose(T.numpy(), T.numpy()), torch.eye(4, dtype=torch.float64)
    )


class _Fake(torch.utils.data.Dataset):
    def __len__(self):
        return 23

    def __getitem__(self, i):
        return i


def test_sampler_resumes_mid_epoch():
    full = ResumableSampler(_Fake(), seed=8)
    full.set_position(3, 0)
    order = list(full)
    assert sorted(order) == list(range(23))
    part = ResumableSampler(_Fake(), seed=8)
    part.set_position(3, 10)
    assert list(part) == order[10:] and len(part) == 13
    other = ResumableSampler(_Fake(), seed=8)
    other.set_position(4, 0)
    assert list(other) != order  # reshuffled per epoch


@pytest.mark.parametrize("rank", [0, 1])
def test_sampler_shards_across_ranks(rank):
    s = ResumableSampler(_Fake(), num_replicas=2, rank=rank, seed=0)
    s.set_position(0, 0)
    mine = list(s)
    s2 = ResumableSampler(_Fake(), num_replicas=2, rank=1 - rank, seed=0)
    s2.set_position(0, 0)
    assert len(mine) == 11 and not set(mine) & set(s2)
