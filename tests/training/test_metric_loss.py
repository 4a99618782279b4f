"""Metric losses on dense correspondences: InfoNCE and hardest-contrastive."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from byoc_cli.training.metric_loss import hardest_contrastive, info_nce, sample_matches


def _setup(n: int = 64, dim: int = 16, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    feats = F.normalize(torch.randn(n, dim, generator=gen), dim=1)
    points = torch.rand(n, 3, generator=gen) * 10.0
    matches = torch.stack([torch.arange(n), torch.arange(n)], dim=1)
    return feats, points, matches


def test_matching_features_give_a_low_loss_and_random_ones_a_high_one():
    feats, points, matches = _setup()
    good = info_nce(feats, feats, matches, points, temperature=0.05)
    shuffled = feats[torch.randperm(len(feats), generator=torch.Generator().manual_seed(1))]
    bad = info_nce(feats, shuffled, matches, points, temperature=0.05)
    assert good < 0.5 < bad


def test_close_negatives_are_masked():
    feats, points, matches = _setup(8)
    # two points at the same place with identical features: unmasked, they would be confused
    feats = feats.clone()
    feats[1] = feats[0]
    points = points.clone()
    points[1] = points[0]
    masked = info_nce(feats, feats, matches, points, temperature=0.05, safe_radius=0.1)
    unmasked = info_nce(feats, feats, matches, points, temperature=0.05, safe_radius=0.0)
    assert masked < unmasked


def test_fewer_than_two_matches_give_zero_with_a_gradient_path():
    feats, points, _ = _setup(4)
    feats = feats.clone().requires_grad_(True)
    loss = info_nce(feats, feats, torch.zeros(1, 2, dtype=torch.int64), points)
    assert loss.item() == 0.0
    loss.backward()
    assert feats.grad is not None


def test_gradcheck_float64():
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(6, 4, dtype=torch.float64, generator=gen, requires_grad=True)
    b = torch.randn(6, 4, dtype=torch.float64, generator=gen, requires_grad=True)
    points = torch.rand(6, 3, dtype=torch.float64, generator=gen) * 5
    matches = torch.stack([torch.arange(6), torch.arange(6)], dim=1)
    assert torch.autograd.gradcheck(
        lambda x, y: info_nce(x, y, matches, points, temperature=0.5), (a, b)
    )


def test_sample_matches():
    matches = torch.stack([torch.arange(100), torch.arange(100)], dim=1)
    gen = torch.Generator().manual_seed(0)
    picked = sample_matches(matches, 10, gen)
    assert picked.shape == (10, 2) and len(set(picked[:, 0].tolist())) == 10
    assert sample_matches(matches[:5], 10, gen).shape == (5, 2)


def test_hardest_contrastive_by_hand():
    # two matched pairs on a circle of unit features, 10 m apart (no masking):
    # a0 = b0 = e0; a1 = b1 = (cos t, sin t). Positive distances 0; each anchor's hardest
    # negative is the other one at distance d = 2 sin(t / 2)
    t = 1.0
    e = torch.tensor([[1.0, 0.0], [torch.cos(torch.tensor(t)), torch.sin(torch.tensor(t))]])
    points = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    matches = torch.tensor([[0, 0], [1, 1]])
    d = 2 * torch.sin(torch.tensor(t / 2))
    expected = torch.relu(1.4 - d) ** 2  # pos term 0; both directions the same
    got = hardest_contrastive(e, e, matches, points)
    assert torch.allclose(got, expected, atol=1e-5)
    # beyond the negative margin and within the positive one: zero
    far = torch.tensor([[1.0, 0.0], [-1.0, 0.0]])
    assert hardest_contrastive(far, far, matches, points).item() < 1e-8
    # a positive pair 0.5 apart costs (0.5 - 0.1)^2 / 2 (mean over the two positives)
    b = far.clone()
    b[0] = torch.tensor([torch.cos(torch.tensor(0.5)), torch.sin(torch.tensor(0.5))])
    pos = (2 * torch.sin(torch.tensor(0.25)) - 0.1) ** 2 / 2
    assert torch.allclose(hardest_contrastive(far, b, matches, points), pos, atol=1e-5)


def test_hardest_contrastive_low_for_matching_features_high_for_random_ones():
    feats, points, matches = _setup()
    spread = torch.eye(64)[:, :64]  # orthogonal features: negatives at sqrt(2) > 1.4
    assert hardest_contrastive(spread, spread, matches, points).item() < 1e-8
    shuffled = feats[torch.randperm(len(feats), generator=torch.Generator().manual_seed(1))]
    assert hardest_contrastive(feats, shuffled, matches, points) > 0.5


def test_hardest_contrastive_masks_close_negatives():
    _, points, matches = _setup(8)
    spread = torch.eye(8)
    spread[1] = spread[0]  # two points at the same place with identical features
    points = points.clone()
    points[1] = points[0]
    masked = hardest_contrastive(spread, spread, matches, points, safe_radius=0.1)
    unmasked = hardest_contrastive(spread, spread, matches, points, safe_radius=0.0)
    assert masked.item() < 1e-8 < unmasked.item()


def test_hardest_contrastive_when_every_negative_is_masked_or_too_few_matches():
    feats, points, matches = _setup(4)
    same_place = torch.zeros(4, 3)
    assert hardest_contrastive(feats, feats, matches, same_place).item() < 1e-8  # pos only: 0
    grad = feats.clone().requires_grad_(True)
    loss = hardest_contrastive(grad, grad, torch.zeros(1, 2, dtype=torch.int64), points)
    assert loss.item() == 0.0
    loss.backward()
    assert grad.grad is not None


def test_hardest_contrastive_gradcheck_float64():
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(6, 4, dtype=torch.float64, generator=gen)
    b = torch.randn(6, 4, dtype=torch.float64, generator=gen)
    a = (a / a.norm(dim=1, keepdim=True)).requires_grad_(True)
    b = (b / b.norm(dim=1, keepdim=True)).requires_grad_(True)
    points = torch.rand(6, 3, dtype=torch.float64, generator=gen) * 5
    matches = torch.stack([torch.arange(6), torch.arange(6)], dim=1)
    assert torch.autograd.gradcheck(
        lambda x, y: hardest_contrastive(x, y, matches, points, neg_margin=2.0), (a, b)
    )
