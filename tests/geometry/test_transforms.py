import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.geometry import (
    apply_transform,
    compose,
    invert_transform,
    make_transform,
    random_rigid_transform,
    rotation_error_deg,
    translation_error,
)
from byoc_cli.geometry.transforms import (
    axis_angle_matrices,
    axis_angle_matrix,
    axis_angle_to_matrix,
)


def test_apply_hand_worked_example():
    # 90 deg about z then translate by (1, 2, 3): (1, 0, 0) -> (0, 1, 0) + t
    R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    T = make_transform(R, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    p = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    expected = torch.tensor([[1.0, 3.0, 3.0], [1.0, 2.0, 4.0]], dtype=torch.float64)
    torch.testing.assert_close(apply_transform(T, p), expected)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_invert_and_compose_cancel(seed):
    g = torch.Generator().manual_seed(seed)
    T_b_a = random_rigid_transform(170, 3.0, generator=g)
    T_c_b = random_rigid_transform(170, 3.0, generator=g)
    points_a = torch.randn(7, 3, generator=g, dtype=torch.float64)
    T_c_a = compose(T_c_b, T_b_a)
    torch.testing.assert_close(
        apply_transform(T_c_a, points_a), apply_transform(T_c_b, apply_transform(T_b_a, points_a))
    )
    torch.testing.assert_close(
        compose(invert_transform(T_b_a), T_b_a), torch.eye(4, dtype=torch.float64)
    )
    R = T_b_a[:3, :3]
    assert torch.linalg.det(R).item() == pytest.approx(1.0, abs=1e-12)


def test_rotation_error_known_angles():
    for deg in (0.0, 1e-4, 5.0, 90.0, 179.0):
        R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(deg)], dtype=torch.float64))
        assert rotation_error_deg(R, torch.eye(3, dtype=torch.float64)).item() == pytest.approx(
            deg, abs=1e-5
        )


def test_translation_error():
    T = make_transform(torch.eye(3), torch.tensor([3.0, 4.0, 0.0]))
    assert translation_error(T, torch.eye(4)).item() == pytest.approx(5.0)


def test_random_transform_bounds_and_seed():
    g1 = torch.Generator().manual_seed(3)
    g2 = torch.Generator().manual_seed(3)
    for _ in range(20):
        T1 = random_rigid_transform(80, 0.5, generator=g1)
        T2 = random_rigid_transform(80, 0.5, generator=g2)
        assert torch.equal(T1, T2)
        assert rotation_error_deg(T1, torch.eye(4)).item() < 80 + 1e-9
        assert torch.linalg.vector_norm(T1[:3, 3]).item() < 0.5


def test_shape_errors():
    with pytest.raises(ShapeError, match=r"\(\.\.\., 4, 4\)"):
        apply_transform(torch.eye(3), torch.zeros(2, 3))
    with pytest.raises(ShapeError, match="points_src"):
        apply_transform(torch.eye(4), torch.zeros(2, 2))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-4.0, 4.0), min_size=3, max_size=3))
def test_the_numpy_rotation_of_a_vector_is_the_torch_one(vector):
    R = axis_angle_matrix(vector)
    expected = axis_angle_to_matrix(torch.tensor(vector, dtype=torch.float64)).numpy()
    assert R.shape == (3, 3)
    assert abs(R - expected).max() < 1e-12
    assert abs(R.T @ R - torch.eye(3).double().numpy()).max() < 1e-12


@settings(max_examples=30, deadline=None)
@given(st.lists(st.lists(st.floats(-4.0, 4.0), min_size=3, max_size=3), min_size=1, max_size=6))
def test_the_numpy_rotations_of_vectors_are_the_torch_ones(vectors):
    vectors[0] = [0.0, 0.0, 0.0]  # the identity among them
    R = axis_angle_matrices(np.array(vectors))
    expected = axis_angle_to_matrix(torch.tensor(vectors, dtype=torch.float64)).numpy()
    assert R.shape == (len(vectors), 3, 3)
    assert abs(R - expected).max() < 1e-12
    assert np.array_equal(R[0], np.eye(3))
