import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import RegistrationError, ShapeError
from byoc_cli.fitting import FitResult, randomized_procrustes, ransac, spatial_compatibility
from byoc_cli.fitting.compatibility import _pairwise
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


def outlier_problem(seed, k=1000, inlier_share=0.04, noise=0.005, scale=2.0):
    """``k`` correspondences in a cube of side ``2 scale``: a share moved by a random ``T``
    (with noise), the rest uniform in the cube; returns ``T, p, q, inlier``."""
    g = torch.Generator().manual_seed(seed)
    T = random_rigid_transform(180, 2.0, generator=g)
    p = (torch.rand(k, 3, generator=g, dtype=F64) * 2 - 1) * scale
    q = apply_transform(T, p) + noise * torch.randn(k, 3, generator=g, dtype=F64)
    inlier = torch.zeros(k, dtype=torch.bool)
    inlier[torch.randperm(k, generator=g)[: round(inlier_share * k)]] = True
    q[~inlier] = (torch.rand(int((~inlier).sum()), 3, generator=g, dtype=F64) * 2 - 1) * scale
    return T, p, q, inlier


def naive_compatibility(p, q, sigma):
    """The hard compatibility and the second-order one, one entry at a time."""
    k = len(p)
    H = torch.zeros(k, k, dtype=F64)
    for i in range(k):
        for j in range(k):
            d = abs(float((p[i] - p[j]).norm()) - float((q[i] - q[j]).norm()))
            H[i, j] = float(d < sigma)
    SC2 = torch.zeros(k, k, dtype=F64)
    for i in range(k):
        for j in range(k):
            SC2[i, j] = H[i, j] * sum(H[i, m] * H[m, j] for m in range(k))
    return H, SC2


def test_hand_worked_five_points_with_one_outlier():
    # 90 deg about z then (1, 2, 3); the 5th correspondence is off by 5 (a 3-4-5 triangle)
    R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    T = make_transform(R, torch.tensor([1.0, 2.0, 3.0], dtype=F64))
    p = torch.tensor(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]],
        dtype=F64,
    )
    q = apply_transform(T, p)
    q[4] += torch.tensor([3.0, 4.0, 0.0], dtype=F64)
    fit = spatial_compatibility(p, q, inlier_threshold=0.1)
    assert isinstance(fit, FitResult)
    torch.testing.assert_close(fit.T_tgt_src, T, rtol=0, atol=1e-12)
    assert fit.inlier_mask.tolist() == [True, True, True, True, False]
    assert fit.num_inliers == 4
    assert fit.score == pytest.approx(0.0, abs=1e-12)


def test_compatibility_matrices_match_a_naive_reference():
    _, p, q, _ = outlier_problem(1, k=40, inlier_share=0.5)
    H, near = _pairwise(p, q, sigma=0.1, radius=0.5)
    H_ref, SC2_ref = naive_compatibility(p, q, 0.1)
    torch.testing.assert_close(H.double(), H_ref)
    torch.testing.assert_close(((H @ H) * H).double(), SC2_ref)
    assert torch.equal(near, torch.cdist(p, p) <= 0.5)
    assert bool(H.diagonal().eq(1).all())


@pytest.mark.parametrize("seed", range(5))
def test_recovers_a_transform_from_four_percent_inliers_where_ransac_does_worse(seed):
    # 40 inliers among 960 uniform outliers: RANSAC draws an all-inlier triplet once in
    # C(1000, 3) / C(40, 3) = 1.7e4 draws, so 10000 draws (100 times the 100 candidates of
    # the compatibility estimator) find it with probability 0.45
    T, p, q, inlier = outlier_problem(seed)
    fit = spatial_compatibility(p, q, inlier_threshold=0.03)
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 0.5
    assert float(translation_error(fit.T_tgt_src, T)) < 0.02
    assert fit.num_inliers >= int(inlier.sum()) - 2
    assert fit.iterations == 100  # 10 % of the 1000 correspondences are seeds


def test_ransac_at_a_hundred_times_the_budget_finds_fewer():
    found = {"sc2": 0, "ransac": 0}
    for seed in range(5):
        T, p, q, _ = outlier_problem(seed)
        fits = {
            "sc2": spatial_compatibility(p, q, 0.03),
            "ransac": ransac(
                p, q, 0.03, max_iterations=10_000, generator=torch.Generator().manual_seed(seed)
            ),
        }
        for name, fit in fits.items():
            found[name] += float(rotation_error_deg(fit.T_tgt_src, T)) < 1.0
    assert found["sc2"] == 5
    assert found["ransac"] < 5


@pytest.mark.parametrize("share", [0.03, 0.05])
def test_recovers_at_three_and_five_percent_of_two_thousand(share):
    T, p, q, _ = outlier_problem(7, k=2000, inlier_share=share)
    fit = spatial_compatibility(p, q, inlier_threshold=0.03)
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 0.5
    assert float(translation_error(fit.T_tgt_src, T)) < 0.02


def test_cap_keeps_the_highest_weights():
    # 3000 correspondences, the cap of 1000 keeps the weighted ones: the 60 inliers (weight 1)
    # and the first 940 outliers of weight 0.5; without weights the first 1000 hold only 20
    T, p, q, inlier = outlier_problem(3, k=3000, inlier_share=0.02)
    weight = torch.where(inlier, 1.0, 0.5).double()
    weight[~inlier] -= torch.linspace(0, 0.1, int((~inlier).sum()), dtype=F64)
    fit = spatial_compatibility(p, q, 0.03, weight=weight, max_correspondences=1000)
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 0.5
    assert fit.num_inliers >= 55  # the inliers beyond the cap are scored too
    assert fit.iterations == 100


def test_result_describes_the_returned_transform():
    _, p, q, _ = outlier_problem(4, k=500, inlier_share=0.1)
    fit = spatial_compatibility(p, q, 0.03)
    r = torch.linalg.vector_norm(apply_transform(fit.T_tgt_src, p) - q, dim=1)
    assert torch.equal(fit.inlier_mask, r < 0.03)
    assert fit.num_inliers == int((r < 0.03).sum())
    assert fit.score == pytest.approx(float(r[r < 0.03].square().mean().sqrt()))


@pytest.mark.parametrize("seed", [0, 1])
def test_deterministic_whatever_the_generator_and_global_rng_untouched(seed):
    _, p, q, _ = outlier_problem(seed, k=600)
    state = torch.random.get_rng_state()
    a = spatial_compatibility(p, q, 0.03, generator=torch.Generator().manual_seed(seed))
    b = spatial_compatibility(p, q, 0.03, generator=torch.Generator().manual_seed(seed + 99))
    c = spatial_compatibility(p, q, 0.03)
    assert torch.equal(torch.random.get_rng_state(), state)
    assert torch.equal(a.T_tgt_src, b.T_tgt_src) and torch.equal(a.T_tgt_src, c.T_tgt_src)
    assert torch.equal(a.inlier_mask, b.inlier_mask)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_equivariance_under_rigid_motions(seed):
    # moving the source by A and the target by B turns T into B T A^-1: lengths, and so every
    # choice of the estimator, are unchanged
    _, p, q, _ = outlier_problem(seed % 1000, k=300, inlier_share=0.2)
    g = torch.Generator().manual_seed(seed)
    A = random_rigid_transform(180, 5.0, generator=g)
    B = random_rigid_transform(180, 5.0, generator=g)
    fit = spatial_compatibility(p, q, 0.03)
    moved = spatial_compatibility(apply_transform(A, p), apply_transform(B, q), 0.03)
    expected = compose(B, compose(fit.T_tgt_src, invert_transform(A)))
    torch.testing.assert_close(moved.T_tgt_src, expected, rtol=0, atol=1e-6)
    assert torch.equal(moved.inlier_mask, fit.inlier_mask)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(30, 400))
def test_inlier_set_is_permutation_invariant(seed, k):
    # a clean inlier set (20 %) is found whatever the order of the correspondences
    T, p, q, _ = outlier_problem(seed % 1000, k=k, inlier_share=0.2, noise=0.0)
    perm = torch.randperm(k, generator=torch.Generator().manual_seed(seed))
    fit = spatial_compatibility(p, q, 0.03)
    shuffled = spatial_compatibility(p[perm], q[perm], 0.03)
    assert torch.equal(shuffled.inlier_mask, fit.inlier_mask[perm])
    assert float(rotation_error_deg(fit.T_tgt_src, T)) < 1e-4  # arccos near 1


def test_float32_in_float32_out_far_from_the_origin():
    # 20 km from the origin float32 keeps millimetres: the same inliers as near the origin
    T, p, q, _ = outlier_problem(5, k=500, inlier_share=0.1)
    offset = torch.tensor([1e4, -2e4, 5e3], dtype=F64)
    shift = make_transform(torch.eye(3, dtype=F64), offset)
    near = spatial_compatibility(p, q, 0.05)
    far = spatial_compatibility((p + offset).float(), (q + offset).float(), 0.05)
    assert far.T_tgt_src.dtype == torch.float32
    expected = compose(shift, compose(T, invert_transform(shift)))
    assert float(rotation_error_deg(far.T_tgt_src.double(), expected)) < 0.5
    assert abs(far.num_inliers - near.num_inliers) <= 2


# ------------------------------------------------------------- degenerate input, as the others


@pytest.mark.parametrize("k", [0, 1, 2])
def test_fewer_than_three_correspondences_raise_as_the_other_estimators(k):
    p = torch.randn(k, 3, dtype=F64)
    for estimator in (
        lambda: spatial_compatibility(p, p, 0.1),
        lambda: ransac(p, p, 0.1),
        lambda: randomized_procrustes(p, p),
    ):
        with pytest.raises(RegistrationError, match="at least 3"):
            estimator()


def test_three_correspondences():
    T, p, q, _ = outlier_problem(11, k=3, inlier_share=1.0, noise=0.0)
    fit = spatial_compatibility(p, q, 0.01)
    torch.testing.assert_close(fit.T_tgt_src, T, rtol=0, atol=1e-9)
    assert fit.num_inliers == 3


def test_collinear_correspondences_do_not_raise_as_ransac():
    s = torch.linspace(0, 1, 20, dtype=F64)[:, None]
    p = s * torch.tensor([[1.0, 2.0, 3.0]], dtype=F64)
    T, _, _, _ = outlier_problem(12, k=1)
    q = apply_transform(T, p)
    fit = spatial_compatibility(p, q, 0.01)
    assert fit.num_inliers == ransac(p, q, 0.01).num_inliers == 20  # the line; its roll is free
    assert float(torch.linalg.det(fit.T_tgt_src[:3, :3])) == pytest.approx(1.0, abs=1e-12)


def test_identical_points_do_not_raise_as_ransac():
    # every correspondence the same pair: the translation is fixed, the rotation is not
    p = torch.tensor([[1.0, 2.0, 3.0]], dtype=F64).repeat(10, 1)
    q = p + torch.tensor([0.5, 0.0, 0.0], dtype=F64)
    fit = spatial_compatibility(p, q, 0.01)
    assert fit.num_inliers == ransac(p, q, 0.01).num_inliers == 10
    torch.testing.assert_close(apply_transform(fit.T_tgt_src, p), q)
    assert float(torch.linalg.det(fit.T_tgt_src[:3, :3])) == pytest.approx(1.0, abs=1e-12)


def test_no_compatible_pair_still_gives_a_rotation():
    # q = 3 p: no two correspondences keep their length; each seed fits on itself alone
    _, p, _, _ = outlier_problem(13, k=50)
    fit = spatial_compatibility(p, 3 * p, 0.01)
    assert float(torch.linalg.det(fit.T_tgt_src[:3, :3])) == pytest.approx(1.0, abs=1e-12)
    assert torch.isfinite(fit.T_tgt_src).all()


def test_argument_errors():
    p = torch.randn(10, 3, dtype=F64)
    with pytest.raises(ShapeError):
        spatial_compatibility(p[None], p[None], 0.1)
    with pytest.raises(ShapeError):
        spatial_compatibility(p, p[:5], 0.1)
    with pytest.raises(ShapeError):
        spatial_compatibility(p, p, 0.1, weight=torch.ones(9))
    with pytest.raises(ValueError, match="inlier_threshold"):
        spatial_compatibility(p, p, 0.0)
    with pytest.raises(ValueError, match="inlier_threshold"):
        spatial_compatibility(p, p, math.nan)
    with pytest.raises(ValueError, match="k1 and k2"):
        spatial_compatibility(p, p, 0.1, k1=10, k2=20)
    with pytest.raises(ValueError, match="seed_ratio"):
        spatial_compatibility(p, p, 0.1, seed_ratio=0.0)
    with pytest.raises(ValueError, match="max_correspondences"):
        spatial_compatibility(p, p, 0.1, max_correspondences=2)
    with pytest.raises(TypeError):
        spatial_compatibility(p, p, 0.1, magic=1)
