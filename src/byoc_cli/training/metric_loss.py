"""Metric-learning losses on dense correspondences (the ``self-posed`` variant): InfoNCE and
FCGF's hardest-contrastive loss.

``feats_i (M, C)`` and ``feats_j (N, C)`` are unit features of two views; ``matches (K, 2)``
int64 rows ``[index_i, index_j]`` are positive pairs; ``points_i (M, 3)`` places the points
of view ``i`` so that negatives too close to a positive can be masked.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def sample_matches(matches: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """At most ``count`` rows of ``matches (K, 2)``, drawn without replacement."""
    if len(matches) <= count:
        return matches
    pick = torch.randperm(len(matches), generator=generator)[:count]
    return matches[pick.to(matches.device)]


def _matched(
    feats_i: torch.Tensor,
    feats_j: torch.Tensor,
    matches: torch.Tensor,
    points_i: torch.Tensor,
    safe_radius: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The matched features ``a (K, C)``, ``b (K, C)`` and ``near (K, K)``: bool, True where two
    positives' points of view ``i`` lie within ``safe_radius`` (False on the diagonal)."""
    p = points_i[matches[:, 0]]
    near = torch.cdist(p, p) < safe_radius
    near.fill_diagonal_(False)
    return feats_i[matches[:, 0]], feats_j[matches[:, 1]], near


def info_nce(
    feats_i: torch.Tensor,
    feats_j: torch.Tensor,
    matches: torch.Tensor,
    points_i: torch.Tensor,
    *,
    temperature: float = 0.1,
    safe_radius: float = 0.1,
) -> torch.Tensor:
    """Symmetric InfoNCE over the positives of ``matches``; the other positives are negatives.

    Row ``a`` of ``feats_i[matches[:, 0]]`` must pick ``feats_j[matches[a, 1]]`` among the
    features of all matched points of view ``j`` (and the other way round). Negatives whose
    point lies within ``safe_radius`` of the positive's point are masked (they may be true
    matches too).

    Returns:
        A scalar (0 with a zero gradient path when there are fewer than 2 matches).
    """
    if len(matches) < 2:
        return feats_i.sum() * 0.0 + feats_j.sum() * 0.0
    a, b, near = _matched(feats_i, feats_j, matches, points_i, safe_radius)
    logits = (a @ b.T / temperature).masked_fill(near, float("-inf"))
    target = torch.arange(len(matches), device=logits.device)
    return 0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target))


def hardest_contrastive(
    feats_i: torch.Tensor,
    feats_j: torch.Tensor,
    matches: torch.Tensor,
    points_i: torch.Tensor,
    *,
    pos_margin: float = 0.1,
    neg_margin: float = 1.4,
    safe_radius: float = 0.1,
) -> torch.Tensor:
    """FCGF's hardest-contrastive loss over the positives of ``matches``.

    ``pos = mean(relu(|a_k - b_k| - pos_margin)^2)`` pulls matched features together;
    each anchor's HARDEST negative (the closest feature of the other view's matched points,
    leaving out those whose point lies within ``safe_radius`` of the anchor's point) is pushed
    beyond ``neg_margin``: ``neg = mean(relu(neg_margin - min_l |a_k - b_l|)^2)``, in both
    directions. Returns ``pos + (neg_i + neg_j) / 2`` (Choy et al., ICCV 2019; their margins
    0.1 and 1.4 for unit features).

    Returns:
        A scalar (0 with a zero gradient path when there are fewer than 2 matches).
    """
    if len(matches) < 2:
        return feats_i.sum() * 0.0 + feats_j.sum() * 0.0
    a, b, near = _matched(feats_i, feats_j, matches, points_i, safe_radius)
    # (K, K) feature distances; the clamp keeps the square root's gradient finite at 0
    square = a.pow(2).sum(1, keepdim=True) + b.pow(2).sum(1)[None, :] - 2.0 * (a @ b.T)
    dist = square.clamp_min(1e-12).sqrt()
    pos = F.relu(dist.diagonal() - pos_margin).pow(2).mean()
    near.fill_diagonal_(True)  # the positive is no negative either
    far = dist.masked_fill(near, float("inf"))
    hardest_i = far.min(dim=1).values
    hardest_j = far.min(dim=0).values
    usable_i, usable_j = torch.isfinite(hardest_i), torch.isfinite(hardest_j)
    neg_i = F.relu(neg_margin - hardest_i[usable_i]).pow(2).sum() / usable_i.sum().clamp_min(1)
    neg_j = F.relu(neg_margin - hardest_j[usable_j]).pow(2).sum() / usable_j.sum().clamp_min(1)
    return pos + 0.5 * (neg_i + neg_j)
