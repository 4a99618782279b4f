"""`RegisterConfig.mutual` reaches the matching of `estimate_transform` and still registers."""

from __future__ import annotations

import math

import torch

import byoc_cli.pipeline.register as register_module
from byoc_cli.pipeline.features import CloudFeatures
from byoc_cli.pipeline.register import RegisterConfig, estimate_transform


def _cloud(points: torch.Tensor, feats: torch.Tensor) -> CloudFeatures:
    n = len(points)
    return CloudFeatures(points, feats, torch.arange(n), torch.zeros(n, 3, dtype=torch.int64))


def _pair(generator: torch.Generator):
    """400 source points, the target = a known motion of them; features shared up to noise."""
    points = torch.rand(400, 3, generator=generator, dtype=torch.float64) * 2.0
    angle = math.radians(30.0)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0],
         [0.0, 0.0, 1.0]], dtype=torch.float64,
    )  # fmt: skip
    T[:3, 3] = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    feats = torch.nn.functional.normalize(torch.randn(400, 16, generator=generator), dim=1)
    noisy = torch.nn.functional.normalize(feats + 0.3 * torch.randn(400, 16, generator=generator))
    target = points @ T[:3, :3].T + T[:3, 3]
    return _cloud(points, feats), _cloud(target, noisy), T


def test_mutual_filters_the_matches_and_recovers_the_motion(monkeypatch):
    src, tgt, T = _pair(torch.Generator().manual_seed(0))
    seen = []
    real = register_module.ratio_test_correspondences

    def spy(*args, **kwargs):
        seen.append(kwargs.get("mutual"))
        return real(*args, **kwargs)

    monkeypatch.setattr(register_module, "ratio_test_correspondences", spy)
    config = RegisterConfig(estimator="ransac", num_correspondences=400, max_points=0)
    plain = estimate_transform(src, tgt, config, voxel_size=0.02)
    mutual = estimate_transform(
        src, tgt, RegisterConfig(**{**config.__dict__, "mutual": True}), voxel_size=0.02
    )
    assert seen == [False, True]
    assert mutual.num_correspondences < plain.num_correspondences
    for result in (plain, mutual):
        assert torch.allclose(result.T_tgt_src, T, atol=1e-6)
