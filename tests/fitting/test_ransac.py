import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import RegistrationError, ShapeError
from byoc_cli.fitting import FitResult, ransac, required_iterations, weighted_procrustes
from byoc_cli.fitting.ransac import _CandidateScorer, _sample_triplets
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


def outlier_problem(seed, k=400, inlier_share=0.5, noise=0.01, scale=2.0):
    g = torch.Generator().manual_seed(seed)
    T = random_rigid_transform(180, 2.0, generator=g)
    p = (torch.rand(k, 3, generator=g, dtype=F64) * 2 - 1) * scale
    q = apply_transform(T, p) + noise * torch.randn(k, 3, generator=g, dtype=F64)
    outlier = torch.rand(k, generator=g) >= inlier_share
    q[outlier] = (torch.rand(int(outlier.sum()), 3, generator=g, dtype=F64) * 2 - 1) * scale
    return T, p, q, ~outlier


def test_hand_worked_four_points_with_one_outlier():
    # 90 deg about z then (1, 2, 3); the 5th correspondence is off by 5 (a 3-4-5 triangle)
    R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    T = make_transform(R, torch.tensor([1.0, 2.0, 3.0], dtype=F64))
    p = torch.tensor(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]],
        dtype=F64,
    )
    q = torch.tensor(
        [[1.0, 2.0, 3.0], [1.0, 3.0, 3.0], [0.0, 2.0, 3.0], [1.0, 2.0, 4.0], [3.0, 7.0, 4.0]],
        dtype=F64,
    )
    fit = ransac(p, q, inlier_threshold=0.1, edge_length_ratio=None)
    torch.testing.assert_close(fit.T_tgt_src, T, rtol=0, atol=1e-12)
    assert fit.inlier_mask.tolist() == [True, True, True, True, False]
    assert fit.num_inliers == 4
    assert fit.score == pytest.approx(0.0, abs=1e-12)


def test_required_iterations_formula():
    # log(1 - 0.999) / log(1 - 0.5^3) = log(0.001) / log(0.875)
    assert required_iterations(0.5, 0.999) == pytest.approx(math.log(0.001) / math.log(0.875))
    assert required_iterations(0.5, 0.999) == pytest.approx(51.73, abs=0.01)
    assert required_iterations(1.0, 0.999) == 0.0
    assert required_iterations(0.0, 0.999) == math.inf
    assert required_iterations(0.5, 1.0) == math.inf


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(3, 300))
def test_noise_free_recovery(seed, k):
    T, p, q, _ = outlier_problem(seed, k=k, inlier_share=1.0, noise=0.0)
    fit = ransac(p, q, 0.01, generator=torch.Generator().manual_seed(seed))
    torch.testing.assert_close(fit.T_tgt_src, T, rtol=0, atol=1e-9)
    assert fit.num_inliers == k and bool(fit.inlier_mask.all())


@pytest.mark.parametrize(("seed", "k"), [(0, 400), (1, 400), (2, 5000), (3, 1000)])
def test_half_outliers_with_noise(seed, k):
    T, p, q, inlier = outlier_problem(seed, k=k)
    fit = ransac(p, q, 0.05, generator=torch.Generator().manual_seed(seed))
    assert isinstance(fit, FitResult)
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 0.5
    assert float(translation_error(fit.T_tgt_src, T)) < 0.01
    found = fit.inlier_mask
    assert int((found & inlier).sum()) >= 0.97 * int(inlier.sum())  # recall
    assert int((found & ~inlier).sum()) <= 0.03 * int(found.sum())  # precision
    # adaptive stopping: ~52 draws are enough at 50 % inliers, so one batch suffices
    assert fit.iterations < 5000


def test_low_inlier_ratio():
    T, p, q, _ = outlier_problem(4, k=1000, inlier_share=0.1)
    fit = ransac(p, q, 0.05, generator=torch.Generator().manual_seed(4))
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 1.0
    assert float(translation_error(fit.T_tgt_src, T)) < 0.02
    assert fit.iterations >= required_iterations(0.1, 0.999)  # ~6900


def test_iteration_cap_and_confidence_one():
    _, p, q, _ = outlier_problem(5)
    assert ransac(p, q, 0.05, max_iterations=10).iterations == 10
    full = ransac(p, q, 0.05, max_iterations=3000, confidence=1.0, batch_size=512)
    assert full.iterations == 3000


def test_result_describes_the_returned_transform():
    _, p, q, _ = outlier_problem(6)
    fit = ransac(p, q, 0.05)
    r = torch.linalg.vector_norm(apply_transform(fit.T_tgt_src, p) - q, dim=-1)
    assert torch.equal(fit.inlier_mask, r < 0.05)
    assert fit.num_inliers == int((r < 0.05).sum())
    assert fit.score == pytest.approx(float(r[r < 0.05].square().mean().sqrt()), rel=1e-9)
    # the final transform is the Procrustes refit on its inliers (the refits converged)
    refit = weighted_procrustes(p[fit.inlier_mask], q[fit.inlier_mask])
    torch.testing.assert_close(fit.T_tgt_src, refit, rtol=0, atol=1e-12)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), batch=st.sampled_from([64, 1024]))
def test_same_seed_bit_identical_and_global_rng_untouched(seed, batch):
    _, p, q, _ = outlier_problem(seed % 1000, k=300, inlier_share=0.3)
    state = torch.random.get_rng_state()
    a = ransac(p, q, 0.05, generator=torch.Generator().manual_seed(seed), batch_size=batch)
    b = ransac(p, q, 0.05, generator=torch.Generator().manual_seed(seed), batch_size=batch)
    assert torch.equal(a.T_tgt_src, b.T_tgt_src) and torch.equal(a.inlier_mask, b.inlier_mask)
    assert (a.iterations, a.num_inliers, a.score) == (b.iterations, b.num_inliers, b.score)
    assert torch.equal(torch.random.get_rng_state(), state)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_equivariance_under_rigid_motions(seed):
    # the inlier set is found again after moving both clouds; the refit is then equivariant
    _, p, q, _ = outlier_problem(seed % 1000, k=300)
    g = torch.Generator().manual_seed(seed)
    A = random_rigid_transform(180, 5.0, generator=g)
    B = random_rigid_transform(180, 5.0, generator=g)
    fit = ransac(p, q, 0.05, generator=torch.Generator().manual_seed(seed))
    moved = ransac(
        apply_transform(A, p),
        apply_transform(B, q),
        0.05,
        generator=torch.Generator().manual_seed(seed),
    )
    assert torch.equal(fit.inlier_mask, moved.inlier_mask)
    expected = compose(B, compose(fit.T_tgt_src, invert_transform(A)))
    torch.testing.assert_close(moved.T_tgt_src, expected, rtol=0, atol=1e-9)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_permutation_invariance_of_the_inliers(seed):
    _, p, q, _ = outlier_problem(seed % 1000, k=300, noise=0.0)
    perm = torch.randperm(300, generator=torch.Generator().manual_seed(seed))
    fit = ransac(p, q, 0.05, generator=torch.Generator().manual_seed(seed))
    fit_p = ransac(p[perm], q[perm], 0.05, generator=torch.Generator().manual_seed(seed + 1))
    assert torch.equal(fit.inlier_mask[perm], fit_p.inlier_mask)
    torch.testing.assert_close(fit.T_tgt_src, fit_p.T_tgt_src, rtol=0, atol=1e-9)
    assert float(torch.linalg.det(fit_p.T_tgt_src[:3, :3])) == pytest.approx(1.0, abs=1e-12)


def test_float32_input_and_far_from_origin():
    T, p, q, _ = outlier_problem(7, k=1000)
    shift = make_transform(torch.eye(3, dtype=F64), torch.tensor([500.0, -300.0, 80.0], dtype=F64))
    fit = ransac(apply_transform(shift, p).float(), apply_transform(shift, q).float(), 0.05)
    assert fit.T_tgt_src.dtype == torch.float32
    T_true = compose(shift, compose(T, invert_transform(shift)))
    assert float(rotation_error_deg(fit.T_tgt_src, T_true)) < 0.5
    # a small rotation error times the 600 m offset moves t; compare on the cloud instead
    moved = apply_transform(shift, p)
    gap = apply_transform(fit.T_tgt_src.double(), moved) - apply_transform(T_true, moved)
    assert float(torch.linalg.vector_norm(gap, dim=-1).max()) < 0.02


@pytest.mark.parametrize(
    ("scale", "threshold", "dtype"), [(2.0, 0.05, torch.float32), (50.0, 0.05, F64)]
)
def test_candidate_scorer_matches_direct_residuals(scale, threshold, dtype):
    _, p, q, _ = outlier_problem(8, k=2000, scale=scale, noise=0.03)
    scorer = _CandidateScorer(p, q, threshold)
    assert scorer.dtype == dtype
    g = torch.Generator().manual_seed(8)
    idx = _sample_triplets(2000, 256, g)
    T = weighted_procrustes(p[idx], q[idx], warn_degenerate=False)
    count, err = scorer(T)
    r2 = (apply_transform(T, p.expand(256, -1, -1)) - q).square().sum(-1)
    inlier = r2 < threshold**2
    # counts may differ only for residuals within rounding of the threshold
    near = ((r2 - threshold**2).abs() < 1e-3 * threshold**2).sum(-1)
    assert bool(((count - inlier.sum(-1)).abs() <= near).all())
    exact = count == inlier.sum(-1)
    torch.testing.assert_close(
        err[exact], (r2 * inlier).sum(-1)[exact], rtol=1e-3, atol=1e-3 * threshold**2
    )


@pytest.mark.parametrize("k", [3, 4, 10, 1000])
def test_sample_triplets_distinct_and_uniform(k):
    g = torch.Generator().manual_seed(k)
    idx = _sample_triplets(k, 30000, g)
    assert idx.dtype == torch.int64 and idx.shape == (30000, 3)
    assert bool((idx >= 0).all() & (idx < k).all())
    assert bool((idx[:, 0] != idx[:, 1]).all() & (idx[:, 0] != idx[:, 2]).all())
    assert bool((idx[:, 1] != idx[:, 2]).all())
    if k <= 10:  # every index equally likely in every position (loose 6-sigma bound)
        for col in range(3):
            freq = torch.bincount(idx[:, col], minlength=k).double() / 30000
            assert float((freq - 1 / k).abs().max()) < 6 * math.sqrt(1 / k / 30000)


def test_edge_length_check_rejecting_everything_returns_identity():
    # q = 2 p: every triangle is twice as large in the target, so all fail the 0.9 check
    _, p, _, _ = outlier_problem(9, k=50)
    with pytest.warns(UserWarning, match="edge-length"):
        fit = ransac(p, 2 * p, 0.05, max_iterations=500)
    torch.testing.assert_close(fit.T_tgt_src, torch.eye(4, dtype=F64))
    assert fit.iterations == 500


def test_edge_length_check_off_still_recovers():
    T, p, q, _ = outlier_problem(10)
    fit = ransac(p, q, 0.05, edge_length_ratio=None)
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 0.5


@pytest.mark.parametrize("k", [0, 1, 2])
def test_fewer_than_three_correspondences_raise(k):
    p = torch.randn(k, 3, dtype=F64)
    with pytest.raises(RegistrationError, match="at least 3"):
        ransac(p, p, 0.1)


def test_three_correspondences():
    T, p, q, _ = outlier_problem(11, k=3, inlier_share=1.0, noise=0.0)
    fit = ransac(p, q, 0.01)
    torch.testing.assert_close(fit.T_tgt_src, T, rtol=0, atol=1e-9)
    assert fit.num_inliers == 3


def test_collinear_correspondences_do_not_raise():
    s = torch.linspace(0, 1, 20, dtype=F64)[:, None]
    p = s * torch.tensor([[1.0, 2.0, 3.0]], dtype=F64)
    T, _, _, _ = outlier_problem(12, k=1)
    fit = ransac(p, apply_transform(T, p), 0.01)
    assert fit.num_inliers == 20  # the line is fitted; the roll about it is arbitrary
    assert float(torch.linalg.det(fit.T_tgt_src[:3, :3])) == pytest.approx(1.0, abs=1e-12)


def test_argument_errors():
    p = torch.randn(10, 3, dtype=F64)
    with pytest.raises(ShapeError):
        ransac(p[None], p[None], 0.1)
    with pytest.raises(ShapeError):
        ransac(p, p[:5], 0.1)
    with pytest.raises(ValueError, match="inlier_threshold"):
        ransac(p, p, 0.0)
    with pytest.raises(ValueError, match="confidence"):
        ransac(p, p, 0.1, confidence=0.0)
    with pytest.raises(ValueError, match="edge_length_ratio"):
        ransac(p, p, 0.1, edge_length_ratio=1.5)
    with pytest.raises(ValueError):
        ransac(p, p, 0.1, max_iterations=0)
