"""Up axis and turns about it (geometry/orientation.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.orientation import aligning, turn_about, up_axis
from byoc_cli.geometry.transforms import random_rigid_transform
from tests.pipeline._rooms import ROOM, sample_boxes


def _room(seed: int = 0) -> np.ndarray:
    return sample_boxes(ROOM, 4000, np.random.default_rng(seed))


def test_the_up_axis_of_a_room_is_its_vertical():
    axis = up_axis(_room())
    assert abs(axis[2]) > 0.99


def test_the_up_axis_turns_with_the_room():
    T = random_rigid_transform(180.0, 1.0, generator=torch.Generator().manual_seed(3)).numpy()
    room = _room() @ T[:3, :3].T + T[:3, 3]
    assert abs(up_axis(room) @ T[:3, 2]) > 0.99


def _planes(counts: dict[int, int], size=(6.0, 5.0, 2.5), seed: int = 1) -> np.ndarray:
    """Points on the faces of a box ``size`` across, ``counts[axis]`` on each face across
    ``axis`` (0, 1: walls; 2: floor and ceiling)."""
    rng = np.random.default_rng(seed)
    half = np.array(size) / 2
    out = []
    for axis, n in counts.items():
        for side in (-1.0, 1.0):
            p = rng.uniform(-half, half, (n, 3))
            p[:, axis] = side * half[axis]
            out.append(p)
    return np.concatenate(out)


def test_a_room_wider_than_tall_is_told_from_its_walls():
    """A room 6 x 5 x 2.5 m whose walls hold three times the points of its floor and ceiling:
    the axis is the one the room is thinnest along, not a wall's normal."""
    assert abs(up_axis(_planes({0: 3000, 1: 3000, 2: 1000}))[2]) > 0.99


def test_a_ground_alone_gives_its_normal():
    """A street's ground with a few poles: one main direction, the ground's normal."""
    ground = _planes({2: 4000}, size=(40.0, 30.0, 0.0))[:4000]
    ground[:, 2] += np.random.default_rng(2).normal(0.0, 0.01, len(ground))
    assert abs(up_axis(ground)[2]) > 0.99


def test_the_up_axis_is_seeded():
    a = up_axis(_room(), generator=torch.Generator().manual_seed(5))
    b = up_axis(_room(), generator=torch.Generator().manual_seed(5))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("bad", [np.zeros((2, 3)), np.zeros((5, 2)), np.zeros(3)])
def test_the_up_axis_refuses_what_is_not_a_cloud(bad):
    with pytest.raises(ShapeError):
        up_axis(bad)


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1),
    st.floats(-360, 360),
    st.lists(st.floats(-5, 5), min_size=3, max_size=3),
)
def test_a_turn_is_rigid_and_keeps_its_axis_and_centre(axis, degrees, centre):
    T = turn_about(np.array(axis), degrees, np.array(centre))
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    on_axis = np.array(centre) + 2.0 * np.array(axis)
    np.testing.assert_allclose(T[:3, :3] @ on_axis + T[:3, 3], on_axis, atol=1e-9)


def test_four_quarter_turns_are_none():
    T = turn_about(np.array([0.0, 0.0, 1.0]), 90.0, np.array([1.0, 2.0, 0.0]))
    np.testing.assert_allclose(np.linalg.matrix_power(T, 4), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


def test_a_turn_refuses_a_zero_axis():
    with pytest.raises(ShapeError):
        turn_about(np.zeros(3), 90.0, np.zeros(3))


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    st.lists(st.floats(-5, 5), min_size=3, max_size=3),
)
def test_aligning_turns_one_direction_onto_the_other_about_the_centre(a, b, c):
    a, b, c = np.array(a), np.array(b), np.array(c)
    assume(np.linalg.norm(a) > 0.1 and np.linalg.norm(b) > 0.1)
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    assume(a @ b > -0.99)
    T = aligning(a, b, c)
    assert np.allclose(T[:3, :3] @ a, b, atol=1e-9)
    assert np.allclose(T[:3, :3] @ c + T[:3, 3], c, atol=1e-9)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    # the smallest rotation: its angle is the angle between the two directions
    angle = math.degrees(math.acos(min(1.0, (np.trace(T[:3, :3]) - 1) / 2)))
    # (the angle from the trace loses digits near 0: 1e-4 deg)
    assert angle == pytest.approx(math.degrees(math.acos(min(1.0, a @ b))), abs=1e-4)


def test_aligning_parallel_directions_is_the_identity_and_opposite_ones_are_refused():
    assert np.allclose(
        aligning(np.array([0, 0, 2.0]), np.array([0, 0, 1.0]), np.ones(3)), np.eye(4)
    )
    with pytest.raises(ShapeError, match="opposite"):
        aligning(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]), np.zeros(3))
    with pytest.raises(ShapeError):
        aligning(np.zeros(3), np.array([0, 0, 1.0]), np.zeros(3))
