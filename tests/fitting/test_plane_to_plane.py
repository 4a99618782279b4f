"""The plane-to-plane (generalized ICP) step: recovery, its reference cost, weights,
degenerate input."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.fitting.plane_to_plane import disc_covariances, plane_to_plane_step
from byoc_cli.geometry.transforms import apply_transform, axis_angle_to_matrix, make_transform
from tests.fitting._surfaces import box_surface, motion


def _iterate(p, n_p, q, n_q, steps=10, weights=None):
    T = torch.eye(4, dtype=torch.float64)
    for _ in range(steps):
        R = T[:3, :3]
        step = plane_to_plane_step(apply_transform(T, p), n_p @ R.T, q, n_q, weights)
        T = step.T @ T
    return T, step


def _cost(T, p, n_p, q, n_q, flatness=1e-3):
    """The generalized-ICP cost at ``T``, written out naively (the reference)."""
    R = T[:3, :3]
    total = torch.zeros((), dtype=torch.float64)
    for i in range(len(p)):
        C = R @ disc_covariances(n_p[i : i + 1], flatness)[0] @ R.T
        C = C + disc_covariances(n_q[i : i + 1], flatness)[0]
        d = q[i] - (R @ p[i] + T[:3, 3])
        total = total + d @ torch.linalg.solve(C, d)
    return float(total)


def test_recovers_a_known_motion_on_a_box(generator):
    q, n = box_surface(3000, generator)
    T_true = motion(4.0, [0.03, -0.02, 0.01])  # maps p onto q
    p = apply_transform(torch.linalg.inv(T_true), q)
    n_p = n @ T_true[:3, :3]  # the source's normals, in the source frame
    T, step = _iterate(p, n_p, q, n)
    assert torch.allclose(T, T_true, atol=1e-8)
    assert step.rank == 6 and step.eigenvalues[-1] == 1.0


def test_a_step_lowers_the_naive_cost_and_the_normals_sign_does_not_matter(generator):
    q, n = box_surface(60, generator)
    T_true = motion(6.0, [0.05, 0.02, -0.04])
    p = apply_transform(torch.linalg.inv(T_true), q)
    n_p = n @ T_true[:3, :3]
    eye = torch.eye(4, dtype=torch.float64)
    step = plane_to_plane_step(p, n_p, q, n)
    assert _cost(step.T, p, n_p, q, n) < 0.05 * _cost(eye, p, n_p, q, n)
    flipped = plane_to_plane_step(p, -n_p, q, -n)
    assert torch.allclose(flipped.T, step.T, atol=1e-12)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.1, 10.0))
def test_weights_scale_and_order_do_not_change_the_step(seed, scale):
    g = torch.Generator().manual_seed(seed)
    q, n = box_surface(200, g)
    T_true = motion(3.0, [0.02, 0.0, 0.01])
    p = apply_transform(torch.linalg.inv(T_true), q)
    w = torch.rand(200, generator=g, dtype=torch.float64)
    base = plane_to_plane_step(p, n, q, n, w)
    scaled = plane_to_plane_step(p, n, q, n, w * scale)
    order = torch.randperm(200, generator=g)
    shuffled = plane_to_plane_step(p[order], n[order], q[order], n[order], w[order])
    assert torch.allclose(base.T, scaled.T, atol=1e-9)
    assert torch.allclose(base.T, shuffled.T, atol=1e-9)


@pytest.mark.parametrize("count", [0, 1, 2])
def test_too_few_points_give_the_identity_with_rank_0(count):
    p = torch.zeros(count, 3, dtype=torch.float64)
    n = torch.zeros(count, 3, dtype=torch.float64)
    n[:, 2] = 1.0
    step = plane_to_plane_step(p, n, p + 0.1, n)
    assert step.rank == 0 and torch.equal(step.T, torch.eye(4, dtype=torch.float64))
    zero = plane_to_plane_step(*(torch.ones(5, 3, dtype=torch.float64),) * 4, torch.zeros(5))
    assert zero.rank == 0


def test_shapes_must_agree():
    with pytest.raises(ShapeError, match=r"\(K, 3\)"):
        plane_to_plane_step(
            torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(5, 3), torch.zeros(4, 3)
        )


def test_the_step_solves_the_normal_equations_written_out_point_by_point(generator):
    """The step's ``H`` and ``g`` (three broadcast products and one matrix product) against
    ``sum_i J_i^T M_i J_i`` and ``sum_i J_i^T M_i (q_i - p_i)``, a point at a time."""
    q, n = box_surface(50, generator)
    T_true = motion(5.0, [0.04, -0.01, 0.02])
    p = apply_transform(torch.linalg.inv(T_true), q)
    n_p = n @ T_true[:3, :3]
    c = p.mean(0)
    x = p - c
    radius = torch.sqrt((x**2).sum(1).mean())
    H, g = torch.zeros(6, 6, dtype=torch.float64), torch.zeros(6, dtype=torch.float64)
    for i in range(len(p)):
        M = torch.linalg.inv(
            disc_covariances(n_p[i : i + 1])[0] + disc_covariances(n[i : i + 1])[0]
        )
        a = x[i] / radius
        A = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
        J = torch.cat([A.double(), -torch.eye(3, dtype=torch.float64)], dim=1)
        H += J.T @ M @ J
        g += J.T @ M @ (q[i] - p[i])
    xi = -torch.linalg.solve(H, g)
    R = axis_angle_to_matrix(xi[:3] / radius)
    expected = make_transform(R, c - R @ c + xi[3:])
    assert torch.allclose(plane_to_plane_step(p, n_p, q, n).T, expected, atol=1e-12)
    as_arrays = plane_to_plane_step(*(t.numpy() for t in (p, n_p, q, n)))
    assert torch.equal(as_arrays.T, plane_to_plane_step(p, n_p, q, n).T)
