"""BYOC's losses (the paper's sections 3.1, Registration Loss, and 3.2), exactly.

* residual ``r_i = |R p_i + t - q_i|`` (L2 norm, not squared);
* visual registration loss ``sum_i (w_i / sum w) r_i``;
* geometric registration loss ``mean_i r_i`` (weights act only through the Procrustes fit);
* visual -> geometric transfer (SimSiam):
  ``2 - mean cos(stopgrad(g0), h(g1)) - mean cos(h(g0), stopgrad(g1))``.

Transforms are ``T_tgt_src`` (4x4): ``p`` are source points, ``q`` their matched target
points. Residuals are computed in float64 (the Procrustes precision).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from byoc_cli.errors import ShapeError

#: clamp of the weight sum in the visual loss (all-zero weights give a zero loss, not NaN)
WEIGHT_SUM_EPS = 1e-12


class Registration(NamedTuple):
    """A differentiable registration of two featured clouds.

    Attributes:
        T_tgt_src: ``(4, 4)`` float64 weighted-Procrustes fit.
        points_src, points_tgt: ``(K, 3)`` float64 matched points.
        weight: ``(K,)`` ratio-test weights (differentiable).
        src_idx, tgt_idx: ``(K,)`` int64 indices of the correspondences.
    """

    T_tgt_src: torch.Tensor
    points_src: torch.Tensor
    points_tgt: torch.Tensor
    weight: torch.Tensor
    src_idx: torch.Tensor
    tgt_idx: torch.Tensor


def residuals(
    T_tgt_src: torch.Tensor, points_src: torch.Tensor, points_tgt: torch.Tensor
) -> torch.Tensor:
    """``r_i = |R p_i + t - q_i|``.

    Args:
        T_tgt_src: ``(4, 4)``.
        points_src, points_tgt: ``(K, 3)`` corresponding points.

    Returns:
        ``(K,)`` float64.
    """
    if points_src.shape != points_tgt.shape or points_src.shape[-1] != 3:
        raise ShapeError(
            f"points must both be (K, 3), got {tuple(points_src.shape)}, {tuple(points_tgt.shape)}"
        )
    T = T_tgt_src.to(torch.float64)
    moved = points_src.to(torch.float64) @ T[:3, :3].transpose(0, 1) + T[:3, 3]
    diff = moved - points_tgt.to(torch.float64)
    # sqrt with a safe gradient at r = 0
    return torch.sqrt((diff * diff).sum(-1).clamp_min(1e-24))


def visual_registration_loss(
    T_tgt_src: torch.Tensor,
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    weight: torch.Tensor,
) -> torch.Tensor:
    """``sum_i (w_i / sum w) r_i`` (float64 scalar)."""
    r = residuals(T_tgt_src, points_src, points_tgt)
    w = weight.to(torch.float64)
    return (w * r).sum() / w.sum().clamp_min(WEIGHT_SUM_EPS)


def geometric_registration_loss(
    T_tgt_src: torch.Tensor, points_src: torch.Tensor, points_tgt: torch.Tensor
) -> torch.Tensor:
    """``mean_i r_i`` (float64 scalar)."""
    return residuals(T_tgt_src, points_src, points_tgt).mean()


class Predictor(nn.Module):
    """SimSiam predictor ``h``: Linear 32->32, LayerNorm, ReLU, Linear 32->32."""

    def __init__(self, dim: int = 32, hidden: int = 32) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(dim, hidden),
            nn.LayerNorm(hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, dim),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def transfer_loss(
    feats_0: torch.Tensor, feats_1: torch.Tensor, predictor: nn.Module
) -> torch.Tensor:
    """Visual -> geometric SimSiam loss on corresponding geometric features.

    Args:
        feats_0, feats_1: ``(K, C)`` geometric features of the two clouds at the visual
            correspondences (row k of each is one correspondence).
        predictor: ``h``.

    Returns:
        ``2 - mean cos(sg(g0), h(g1)) - mean cos(h(g0), sg(g1))`` (float32 scalar).
    """
    if feats_0.shape != feats_1.shape:
        raise ShapeError(
            f"feature sets differ in shape: {tuple(feats_0.shape)}, {tuple(feats_1.shape)}"
        )
    g0 = feats_0.float()
    g1 = feats_1.float()
    h0 = predictor(g0)
    h1 = predictor(g1)
    cos_a = F.cosine_similarity(g0.detach(), h1, dim=-1).mean()
    cos_b = F.cosine_similarity(h0, g1.detach(), dim=-1).mean()
    return 2.0 - cos_a - cos_b


def register_features(
    feats_src: torch.Tensor,
    feats_tgt: torch.Tensor,
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    k: int = 200,
) -> Registration:
    """Ratio-test top-k correspondences in both directions and one weighted Procrustes.

    Args:
        feats_src, feats_tgt: ``(N, C)``, ``(M, C)`` unit features.
        points_src, points_tgt: ``(N, 3)``, ``(M, 3)`` the points they describe.
        k: correspondences kept per direction.

    Returns:
        :class:`Registration` (differentiable through the weights).
    """
    from byoc_cli.fitting import weighted_procrustes
    from byoc_cli.matching import ratio_test_correspondences

    corr = ratio_test_correspondences(feats_src.float(), feats_tgt.float(), k=k)
    p = points_src[corr.src_idx].to(torch.float64)
    q = points_tgt[corr.tgt_idx].to(torch.float64)
    T = weighted_procrustes(p, q, corr.weight, warn_degenerate=False)
    return Registration(T, p, q, corr.weight, corr.src_idx, corr.tgt_idx)
