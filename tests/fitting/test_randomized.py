import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import RegistrationError, ShapeError
from byoc_cli.fitting import FitResult, randomized_procrustes, weighted_procrustes
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


def outlier_problem(seed, k=400, inlier_share=0.5, noise=0.01, informative=True):
    """Correspondences with ``inlier_share`` inliers; outliers uniform in the scene box.

    With ``informative`` weights, inliers get weights in [0.3, 1] and outliers in [0, 0.3],
    the way the ratio test tends to rank them; otherwise every weight is uniform in [0, 1].
    """
    g = torch.Generator().manual_seed(seed)
    T = random_rigid_transform(60, 1.0, generator=g)
    p = torch.rand(k, 3, generator=g, dtype=F64) * 4 - 2
    q = apply_transform(T, p) + noise * torch.randn(k, 3, generator=g, dtype=F64)
    outlier = torch.rand(k, generator=g) >= inlier_share
    q[outlier] = torch.rand(int(outlier.sum()), 3, generator=g, dtype=F64) * 4 - 2
    u = torch.rand(k, generator=g, dtype=F64)
    w = torch.where(outlier, 0.3 * u, 0.3 + 0.7 * u) if informative else u
    return T, p, q, w, ~outlier


def test_hand_worked_four_points_every_subset_is_exact():
    # 90 deg about z then (1, 2, 3); any subset with 3 distinct points recovers T, subsets
    # with fewer are scored worse unless they happen to be right too: the best score is 0.
    R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    T = make_transform(R, torch.tensor([1.0, 2.0, 3.0], dtype=F64))
    p = torch.tensor(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64
    )
    q = torch.tensor(
        [[1.0, 2.0, 3.0], [1.0, 3.0, 3.0], [0.0, 2.0, 3.0], [1.0, 2.0, 4.0]], dtype=F64
    )
    fit = randomized_procrustes(p, q, torch.ones(4, dtype=F64), num_subsets=10, subset_size=4)
    torch.testing.assert_close(fit.T_tgt_src, T, rtol=0, atol=1e-12)
    assert fit.score == pytest.approx(0.0, abs=1e-12)
    assert fit.iterations == 10
    assert fit.inlier_mask is None and fit.num_inliers is None


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(3, 500))
def test_noise_free_recovery(seed, k):
    g = torch.Generator().manual_seed(seed)
    T = random_rigid_transform(180, 3.0, generator=g)
    p = torch.randn(k, 3, generator=g, dtype=F64)
    q = apply_transform(T, p)
    w = torch.rand(k, generator=g, dtype=F64) + 0.1
    fit = randomized_procrustes(p, q, w, generator=g)
    torch.testing.assert_close(fit.T_tgt_src, T, rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_paper_setting_with_half_outliers_and_informative_weights(seed):
    # 100 subsets of 20 out of 400: every subset holds about 10 outliers, down-weighted but
    # not rejected, so the estimate is biased; a few degrees / cm on a 4 m scene
    T, p, q, w, _ = outlier_problem(seed)
    fit = randomized_procrustes(p, q, w, generator=torch.Generator().manual_seed(seed))
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 3.0
    assert float(translation_error(fit.T_tgt_src, T)) < 0.1


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_small_subsets_with_half_outliers_and_uniform_weights(seed):
    # with 4 correspondences per subset about 1 subset in 16 is outlier-free; the score
    # (a weighted L1 over all correspondences) picks one of those
    T, p, q, w, inlier = outlier_problem(seed, informative=False)
    fit = randomized_procrustes(
        p,
        q,
        w,
        num_subsets=200,
        subset_size=4,
        generator=torch.Generator().manual_seed(seed),
        inlier_threshold=0.05,
    )
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 2.0
    assert float(translation_error(fit.T_tgt_src, T)) < 0.05
    assert fit.num_inliers == int(fit.inlier_mask.sum())
    assert int((fit.inlier_mask & inlier).sum()) >= 0.9 * int(inlier.sum())


def test_score_and_inliers_describe_the_returned_transform():
    _, p, q, w, _ = outlier_problem(5)
    fit = randomized_procrustes(p, q, w, inlier_threshold=0.05)
    assert isinstance(fit, FitResult)
    r = torch.linalg.vector_norm(apply_transform(fit.T_tgt_src, p) - q, dim=-1)
    assert fit.score == pytest.approx(float((w * r).mean()), rel=1e-12)
    assert torch.equal(fit.inlier_mask, r < 0.05)
    assert fit.inlier_mask.dtype == torch.bool and fit.num_inliers == int((r < 0.05).sum())


def test_best_candidate_is_chosen_from_the_drawn_subsets():
    # replay the documented sampling: one randint of shape (num_subsets, subset_size)
    _, p, q, w, _ = outlier_problem(6, k=100)
    fit = randomized_procrustes(p, q, w, 30, 5, torch.Generator().manual_seed(9))
    subsets = torch.randint(100, (30, 5), generator=torch.Generator().manual_seed(9))
    candidates = weighted_procrustes(p[subsets], q[subsets], w[subsets], warn_degenerate=False)
    r = torch.linalg.vector_norm(apply_transform(candidates, p.expand(30, -1, -1)) - q, dim=-1)
    scores = (w * r).mean(-1)
    assert torch.equal(fit.T_tgt_src, candidates[int(scores.argmin())])
    assert fit.score == float(scores.min())


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_same_seed_bit_identical_and_global_rng_untouched(seed):
    _, p, q, w, _ = outlier_problem(seed % 1000, k=200)
    state = torch.random.get_rng_state()
    a = randomized_procrustes(p, q, w, generator=torch.Generator().manual_seed(seed))
    b = randomized_procrustes(p, q, w, generator=torch.Generator().manual_seed(seed))
    assert torch.equal(a.T_tgt_src, b.T_tgt_src) and a.score == b.score
    assert torch.equal(torch.random.get_rng_state(), state)


def test_default_generator_is_seeded():
    _, p, q, w, _ = outlier_problem(7, k=200)
    assert torch.equal(
        randomized_procrustes(p, q, w).T_tgt_src, randomized_procrustes(p, q, w).T_tgt_src
    )


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_equivariance_under_rigid_motions(seed):
    _, p, q, w, _ = outlier_problem(seed % 1000, k=200, informative=False)
    g = torch.Generator().manual_seed(seed)
    A = random_rigid_transform(180, 5.0, generator=g)
    B = random_rigid_transform(180, 5.0, generator=g)
    T = randomized_procrustes(p, q, w, generator=torch.Generator().manual_seed(seed)).T_tgt_src
    T_moved = randomized_procrustes(
        apply_transform(A, p),
        apply_transform(B, q),
        w,
        generator=torch.Generator().manual_seed(seed),
    ).T_tgt_src
    torch.testing.assert_close(
        T_moved, compose(B, compose(T, invert_transform(A))), rtol=0, atol=1e-9
    )


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(1e-3, 1e3))
def test_weight_scale_invariance_and_proper_rotation(seed, scale):
    _, p, q, w, _ = outlier_problem(seed % 1000, k=100)
    a = randomized_procrustes(p, q, w, generator=torch.Generator().manual_seed(seed))
    b = randomized_procrustes(p, q, w * scale, generator=torch.Generator().manual_seed(seed))
    torch.testing.assert_close(a.T_tgt_src, b.T_tgt_src, rtol=0, atol=1e-9)
    assert b.score == pytest.approx(a.score * scale, rel=1e-9)
    assert float(torch.linalg.det(a.T_tgt_src[:3, :3])) == pytest.approx(1.0, abs=1e-12)


def test_float32_in_float32_out():
    T, p, q, w, _ = outlier_problem(8)
    fit = randomized_procrustes(p.float(), q.float(), w.float())
    assert fit.T_tgt_src.dtype == torch.float32
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 2.0


def test_all_zero_weights_still_give_a_rotation():
    _, p, q, _, _ = outlier_problem(9, k=50)
    fit = randomized_procrustes(p, q, torch.zeros(50, dtype=F64))
    assert fit.score == 0.0  # every candidate scores 0: the first one is returned
    assert float(torch.linalg.det(fit.T_tgt_src[:3, :3])) == pytest.approx(1.0)


@pytest.mark.parametrize("k", [0, 1, 2])
def test_fewer_than_three_correspondences_raise(k):
    p = torch.randn(k, 3, dtype=F64)
    with pytest.raises(RegistrationError, match="at least 3"):
        randomized_procrustes(p, p, torch.ones(k, dtype=F64))


def test_three_correspondences_work():
    T, p, q, w, _ = outlier_problem(10, k=3, inlier_share=1.0, noise=0.0)
    fit = randomized_procrustes(p, q, w, subset_size=20)
    assert fit.T_tgt_src.shape == (4, 4)
    assert float(torch.linalg.det(fit.T_tgt_src[:3, :3])) == pytest.approx(1.0)
    # with replacement, some subset holds all three points and fits exactly
    torch.testing.assert_close(fit.T_tgt_src, T, rtol=0, atol=1e-9)


def test_argument_errors():
    p = torch.randn(10, 3, dtype=F64)
    w = torch.ones(10, dtype=F64)
    with pytest.raises(ShapeError):
        randomized_procrustes(p[None], p[None], w[None])
    with pytest.raises(ShapeError):
        randomized_procrustes(p, p, w[:5])
    with pytest.raises(ValueError, match="num_subsets"):
        randomized_procrustes(p, p, w, num_subsets=0)
    with pytest.raises(ValueError, match="inlier_threshold"):
        randomized_procrustes(p, p, w, inlier_threshold=-1.0)
