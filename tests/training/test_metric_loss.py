"""InfoNCE on dense correspondences."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from byoc_cli.training.metric_loss import info_nce, sample_matches


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
