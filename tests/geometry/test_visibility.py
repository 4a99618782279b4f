"""Free space seen from a cloud's origin (geometry/visibility.py): the bins of directions, the
nearest range per bin, which points lie in front of a measured surface, and the share."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.visibility import (
    FACE_BINS,
    MARGIN_SHARE,
    MARGIN_VOXELS,
    cube_bins,
    free_space_share,
    hidden_share,
    in_free_space,
    range_image,
)
from tests._rings import room_scan, wall

VOXEL = 0.025


def _wall(z: float = 3.0, half: float = 1.0, step: float = 0.02) -> torch.Tensor:
    """``(N, 3)`` :func:`tests._rings.wall` as a tensor."""
    return torch.from_numpy(wall(z, half, step))


def test_each_axis_has_its_own_face_and_the_range_is_the_distance():
    axes = torch.tensor(
        [[2.0, 0, 0], [-2.0, 0, 0], [0, 3.0, 0], [0, -3.0, 0], [0, 0, 4.0], [0, 0, -4.0]],
        dtype=torch.float64,
    )
    index, rng = cube_bins(axes)
    faces = (index // (FACE_BINS * FACE_BINS)).tolist()
    assert sorted(faces) == list(range(6))
    assert rng.tolist() == [2.0, 2.0, 3.0, 3.0, 4.0, 4.0]
    centre = FACE_BINS // 2
    assert ((index % (FACE_BINS * FACE_BINS)) == centre * FACE_BINS + centre).all()


def test_bins_cover_the_sphere_once():
    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(20000, 3, generator=g, dtype=torch.float64)
    index, _ = cube_bins(dirs)
    assert int(index.min()) >= 0 and int(index.max()) < 6 * FACE_BINS * FACE_BINS
    assert len(torch.unique(index)) > 0.9 * 6 * FACE_BINS * FACE_BINS / 3  # spread, not few


def test_a_bins_range_is_the_nearest_around_it_and_an_empty_bin_says_nothing():
    far = torch.tensor([[0.0, 0.0, 3.0]], dtype=torch.float64)
    over = 1.5 * 2.0 / FACE_BINS  # a bin and a half over on the +z face, at 1 m
    near = torch.tensor([[over, 0.0, 1.0]], dtype=torch.float64)
    image = range_image(torch.cat([far, near]), grow=2)
    (own,), _ = cube_bins(far)
    assert image[own] == pytest.approx(float(torch.linalg.vector_norm(near)))
    assert torch.isinf(image).sum() == image.numel() - 2  # only the two bins with points
    alone = range_image(far, grow=0)
    assert alone[own] == 3.0 and torch.isinf(alone).sum() == alone.numel() - 1


def test_points_in_front_of_a_measured_wall_are_in_free_space():
    image = range_image(_wall(3.0))
    points = torch.tensor(
        [
            [0.1, 0.1, 1.5],  # in front of the wall: empty space the sensor saw through
            [0.1, 0.1, 3.0],  # on the wall
            [0.1, 0.1, 2.95],  # within the margin
            [0.1, 0.1, 4.0],  # behind it: not seen
            [3.0, 0.1, 0.2],  # a direction with no wall: nothing measured
            [0.0, 0.0, 0.1],  # in the sensor's blind zone
        ],
        dtype=torch.float64,
    )
    free = in_free_space(points, image, VOXEL)
    assert free.inside.tolist() == [True, False, False, False, False, False]
    assert free.seen.tolist() == [True, True, True, True, False, False]


def test_the_margin_is_voxels_plus_a_share_of_the_range():
    image = range_image(_wall(3.0))
    edge = 3.0 * (1 - MARGIN_SHARE) - MARGIN_VOXELS * VOXEL
    points = torch.tensor([[0.0, 0.0, edge - 1e-6], [0.0, 0.0, edge + 1e-6]], dtype=torch.float64)
    assert in_free_space(points, image, VOXEL).inside.tolist() == [True, False]


def test_a_wall_slid_towards_the_sensor_lies_in_its_free_space():
    wall = _wall(3.0)
    share, seen = free_space_share(wall, wall, VOXEL)
    assert share == 0.0 and seen == len(wall)
    slid = wall + torch.tensor([0.3, 0.0, -1.0], dtype=torch.float64)
    share, seen = free_space_share(slid, wall, VOXEL)
    assert share == 1.0 and 0 < seen < len(wall)  # part of it moved out of the wall's view


@settings(max_examples=40, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.integers(3, 400),
    st.floats(0.1, 50.0),
    st.floats(1e-3, 0.5),
)
def test_a_cloud_never_lies_in_its_own_free_space(seed, n, spread, voxel):
    g = torch.Generator().manual_seed(seed)
    points = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * spread
    share, seen = free_space_share(points, points, voxel)
    assert share == 0.0 and 0 <= seen <= n


def test_nothing_to_judge_is_a_share_of_zero():
    wall = _wall(3.0)
    empty = torch.zeros(0, 3, dtype=torch.float64)
    assert free_space_share(empty, wall, VOXEL) == (0.0, 0)
    assert free_space_share(wall, empty, VOXEL) == (0.0, 0)


def test_wrong_shapes_and_voxels_are_refused():
    wall = _wall(3.0)
    with pytest.raises(ShapeError):
        cube_bins(torch.zeros(4, 2))
    with pytest.raises(ShapeError):
        free_space_share(wall, torch.zeros(3), VOXEL)
    with pytest.raises(ShapeError):
        in_free_space(wall, range_image(wall), -1.0)
    with pytest.raises(ShapeError):
        in_free_space(wall, range_image(wall), math.nan)


def test_a_scan_hides_almost_nothing_of_itself_from_its_scanner_and_much_from_outside():
    room = torch.from_numpy(room_scan())
    assert hidden_share(room, 0.05) < 0.01
    assert hidden_share(room + torch.tensor([6.0, 0.0, 0.0], dtype=room.dtype), 0.05) > 0.5
    layered = torch.cat([_wall(3.0), _wall(5.0)])  # the far wall behind the near one
    assert hidden_share(layered, VOXEL) == pytest.approx(0.5, abs=0.01)


def test_hidden_share_of_degenerate_clouds():
    assert hidden_share(torch.zeros(0, 3, dtype=torch.float64), VOXEL) == 0.0
    assert hidden_share(torch.zeros(4, 3, dtype=torch.float64), VOXEL) == 0.0  # at the sensor
    with pytest.raises(ShapeError):
        hidden_share(torch.zeros(4, 2), VOXEL)
    with pytest.raises(ShapeError):
        hidden_share(_wall(), 0.0)
