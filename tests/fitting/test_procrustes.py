import warnings

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.fitting import weighted_procrustes, weighted_residuals
from byoc_cli.geometry import (
    apply_transform,
    compose,
    invert_transform,
    make_transform,
    random_rigid_transform,
    rotation_error_deg,
    translation_error,
)

F64 = torch.float64

# 90 deg about z, (x, y, z) -> (-y, x, z), then t = (1, 2, 3)
RZ90 = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
T_HAND = make_transform(RZ90, torch.tensor([1.0, 2.0, 3.0], dtype=F64))
P_HAND = torch.tensor(
    [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64
)
Q_HAND = torch.tensor(
    [[1.0, 2.0, 3.0], [1.0, 3.0, 3.0], [0.0, 2.0, 3.0], [1.0, 2.0, 4.0]], dtype=F64
)


def det3(T):
    return torch.linalg.det(T[..., :3, :3].double())


def random_problem(seed, k, noise=0.0, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    T = random_rigid_transform(180, 3.0, generator=g)
    p = torch.randn(k, 3, generator=g, dtype=F64) * 2
    q = apply_transform(T, p) + noise * torch.randn(k, 3, generator=g, dtype=F64)
    w = torch.rand(k, generator=g, dtype=F64) + 0.1
    return T, p.to(dtype), q.to(dtype), w.to(dtype)


# --- hand-worked cases ---------------------------------------------------------------------


def test_hand_worked_four_points():
    torch.testing.assert_close(apply_transform(T_HAND, P_HAND), Q_HAND)  # the data are right
    T = weighted_procrustes(P_HAND, Q_HAND, torch.ones(4, dtype=F64))
    torch.testing.assert_close(T, T_HAND, rtol=0, atol=1e-12)


def test_hand_worked_zero_weight_ignores_an_outlier():
    q = Q_HAND.clone()
    q[3] = torch.tensor([50.0, -7.0, 0.0], dtype=F64)  # garbage, weight 0
    T = weighted_procrustes(P_HAND, q, torch.tensor([1.0, 2.0, 0.5, 0.0], dtype=F64))
    torch.testing.assert_close(T, T_HAND, rtol=0, atol=1e-12)


def test_hand_worked_mirror_of_planar_points_is_a_rotation():
    # q = p with x negated; the points lie in z = 0, so the rotation by 180 deg about y,
    # diag(-1, 1, -1), maps them exactly, and it is the only proper rotation that does.
    p = torch.tensor(
        [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -2.0, 0.0]], dtype=F64
    )
    q = p * torch.tensor([-1.0, 1.0, 1.0], dtype=F64)
    T = weighted_procrustes(p, q)
    expected = make_transform(
        torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=F64)), torch.zeros(3, dtype=F64)
    )
    torch.testing.assert_close(T, expected, rtol=0, atol=1e-12)


def test_hand_worked_residuals():
    q = Q_HAND.clone()
    q[1] += torch.tensor([3.0, 4.0, 0.0], dtype=F64)  # off by a 3-4-5 triangle
    r = weighted_residuals(T_HAND, P_HAND, q)
    torch.testing.assert_close(r, torch.tensor([0.0, 5.0, 0.0, 0.0], dtype=F64))


# --- recovery ------------------------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(3, 200))
def test_noise_free_recovery(seed, k):
    T, p, q, w = random_problem(seed, k)
    T_est = weighted_procrustes(p, q, w)
    torch.testing.assert_close(T_est, T, rtol=0, atol=1e-9)


def test_batched_over_leading_dims_matches_one_by_one():
    problems = [random_problem(s, 30, noise=0.05) for s in range(6)]
    p = torch.stack([x[1] for x in problems]).reshape(2, 3, 30, 3)
    q = torch.stack([x[2] for x in problems]).reshape(2, 3, 30, 3)
    w = torch.stack([x[3] for x in problems]).reshape(2, 3, 30)
    T = weighted_procrustes(p, q, w)
    assert T.shape == (2, 3, 4, 4)
    for i, (_, pi, qi, wi) in enumerate(problems):
        torch.testing.assert_close(T.reshape(6, 4, 4)[i], weighted_procrustes(pi, qi, wi))


def test_returns_the_input_dtype_and_device():
    T, p, q, w = random_problem(1, 50, dtype=torch.float32)
    T_est = weighted_procrustes(p, q, w)
    assert T_est.dtype == torch.float32 and T_est.device == p.device
    torch.testing.assert_close(T_est, T.float(), rtol=0, atol=1e-5)
    assert weighted_procrustes(p.double(), q.double()).dtype == F64


def test_noisy_fit_minimises_the_weighted_squared_error():
    # the method weights the covariance by w_hat^2 and the means by w: check optimality of
    # the rotation for that objective against small perturbations
    _, p, q, w = random_problem(7, 40, noise=0.3)
    T = weighted_procrustes(p, q, w)

    def cost(T_):
        mu_p = (w[:, None] * p).sum(0) / w.sum()
        mu_q = (w[:, None] * q).sum(0) / w.sum()
        r = (p - mu_p) @ T_[:3, :3].T - (q - mu_q)
        return float((w**2 * r.square().sum(-1)).sum())

    base = cost(T)
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        dT = random_rigid_transform(2.0, 0.0, generator=g)
        assert cost(compose(dT, T)) >= base - 1e-12


# --- properties ----------------------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(4, 100))
def test_equivariance_under_rigid_motions(seed, k):
    _, p, q, w = random_problem(seed, k, noise=0.2)
    g = torch.Generator().manual_seed(seed + 1)
    A = random_rigid_transform(180, 5.0, generator=g)
    B = random_rigid_transform(180, 5.0, generator=g)
    T = weighted_procrustes(p, q, w)
    T_moved = weighted_procrustes(apply_transform(A, p), apply_transform(B, q), w)
    torch.testing.assert_close(
        T_moved, compose(B, compose(T, invert_transform(A))), rtol=0, atol=1e-9
    )


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(4, 100), scale=st.floats(1e-3, 1e3))
def test_permutation_and_weight_scale_invariance(seed, k, scale):
    _, p, q, w = random_problem(seed, k, noise=0.2)
    perm = torch.randperm(k, generator=torch.Generator().manual_seed(seed))
    T = weighted_procrustes(p, q, w)
    torch.testing.assert_close(weighted_procrustes(p[perm], q[perm], w[perm]), T, rtol=0, atol=1e-9)
    torch.testing.assert_close(weighted_procrustes(p, q, w * scale), T, rtol=0, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(3, 50), mirror=st.booleans())
def test_never_a_reflection(seed, k, mirror):
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(k, 3, generator=g, dtype=F64)
    q = torch.randn(k, 3, generator=g, dtype=F64)
    if mirror:  # the best orthogonal map is a reflection
        q = p * torch.tensor([1.0, 1.0, -1.0], dtype=F64)
    w = torch.rand(k, generator=g, dtype=F64)
    T = weighted_procrustes(p, q, w)
    R = T[:3, :3]
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=F64), rtol=0, atol=1e-12)
    assert abs(float(det3(T)) - 1.0) < 1e-12


def test_gradcheck_points_and_weights():
    _, p, q, w = random_problem(11, 8, noise=0.3)
    inputs = (p.requires_grad_(), q.requires_grad_(), w.requires_grad_())
    assert torch.autograd.gradcheck(weighted_procrustes, inputs)


def test_gradcheck_batched_with_a_reflection_fix():
    g = torch.Generator().manual_seed(12)
    p = torch.randn(2, 6, 3, generator=g, dtype=F64)
    q = p.clone()
    q[0] = torch.randn(6, 3, generator=g, dtype=F64)  # arbitrary
    q[1] = p[1] * torch.tensor([1.0, 1.0, -1.0], dtype=F64) + 0.1 * torch.randn(
        6, 3, generator=g, dtype=F64
    )
    w = torch.rand(2, 6, generator=g, dtype=F64) + 0.2
    inputs = (p.requires_grad_(), q.requires_grad_(), w.requires_grad_())
    assert torch.autograd.gradcheck(weighted_procrustes, inputs)


def test_gradcheck_residuals():
    T, p, q, _ = random_problem(13, 6, noise=0.3)
    inputs = (T.clone().requires_grad_(), p.requires_grad_(), q.requires_grad_())
    assert torch.autograd.gradcheck(weighted_residuals, inputs)


# --- degenerate input ----------------------------------------------------------------------


@pytest.mark.parametrize("k", [0, 1, 2])
def test_too_few_points_warns_and_returns_a_rotation(k):
    _, p, q, w = random_problem(3, 5)
    with pytest.warns(UserWarning, match="degenerate"):
        T = weighted_procrustes(p[:k], q[:k], w[:k])
    assert torch.isfinite(T).all()
    assert abs(float(det3(T)) - 1.0) < 1e-12
    torch.testing.assert_close(T[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64))
    if k == 0:
        torch.testing.assert_close(T, torch.eye(4, dtype=F64))
    else:  # the weighted means still map onto each other
        mu_p = (w[:k, None] * p[:k]).sum(0) / w[:k].sum()
        mu_q = (w[:k, None] * q[:k]).sum(0) / w[:k].sum()
        torch.testing.assert_close(apply_transform(T, mu_p[None])[0], mu_q)
    if k == 2:  # and so does the line through both points
        torch.testing.assert_close(apply_transform(T, p[:2]), q[:2])


def test_three_points_are_enough():
    T, p, q, w = random_problem(4, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        T_est = weighted_procrustes(p, q, w)
    torch.testing.assert_close(T_est, T, rtol=0, atol=1e-9)


def test_collinear_points_warn_and_fit_the_line():
    T, _, _, _ = random_problem(5, 1)
    s = torch.linspace(-2, 3, 6, dtype=F64)[:, None]
    p = s * torch.tensor([[1.0, 2.0, -0.5]], dtype=F64) + torch.tensor([[0.3, 0.1, 0.2]], dtype=F64)
    q = apply_transform(T, p)
    with pytest.warns(UserWarning, match="degenerate"):
        T_est = weighted_procrustes(p, q, torch.rand(6, dtype=F64) + 0.1)
    assert abs(float(det3(T_est)) - 1.0) < 1e-12
    torch.testing.assert_close(apply_transform(T_est, p), q, rtol=0, atol=1e-9)


def test_all_weights_zero_falls_back_to_uniform_weights():
    _, p, q, _ = random_problem(6, 20, noise=0.1)
    with pytest.warns(UserWarning, match="degenerate"):
        T_zero = weighted_procrustes(p, q, torch.zeros(20, dtype=F64))
    torch.testing.assert_close(T_zero, weighted_procrustes(p, q), rtol=0, atol=1e-12)


def test_one_degenerate_batch_element_does_not_spoil_the_others():
    T, p, q, w = random_problem(8, 10)
    w_batch = torch.stack([w, torch.zeros_like(w)])
    with pytest.warns(UserWarning):
        T_batch = weighted_procrustes(p.expand(2, -1, -1), q.expand(2, -1, -1), w_batch)
    torch.testing.assert_close(T_batch[0], T, rtol=0, atol=1e-9)
    torch.testing.assert_close(T_batch[1], T, rtol=0, atol=1e-9)  # noise-free: uniform fits too


def test_warning_can_be_turned_off():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        weighted_procrustes(P_HAND[:2], Q_HAND[:2], warn_degenerate=False)


def test_gradient_is_finite_for_zero_weights_in_a_healthy_fit():
    _, p, q, w = random_problem(9, 10, noise=0.1)
    w = w.clone()
    w[:3] = 0.0
    w.requires_grad_()
    weighted_procrustes(p, q, w)[:3].sum().backward()
    assert torch.isfinite(w.grad).all()


def test_shape_errors():
    with pytest.raises(ShapeError):
        weighted_procrustes(P_HAND, Q_HAND[:3])
    with pytest.raises(ShapeError):
        weighted_procrustes(P_HAND[:, :2], Q_HAND[:, :2])
    with pytest.raises(ShapeError):
        weighted_procrustes(P_HAND, Q_HAND, torch.ones(3, dtype=F64))
    with pytest.raises(ShapeError):
        weighted_residuals(T_HAND, P_HAND, Q_HAND[:2])


def test_large_offsets_are_handled_in_float64():
    # float32 input far from the origin: centring happens in float64
    T, p, q, w = random_problem(10, 100)
    shift = make_transform(
        torch.eye(3, dtype=F64), torch.tensor([1000.0, -2000.0, 500.0], dtype=F64)
    )
    T_est = weighted_procrustes(
        apply_transform(shift, p).float(), apply_transform(shift, q).float(), w.float()
    )
    T_true = compose(shift, compose(T, invert_transform(shift)))
    assert float(rotation_error_deg(T_est, T_true)) < 0.01
    assert float(translation_error(T_est, T_true)) < 0.01
