"""Metric-learning losses on dense correspondences (the ``self-posed`` variant).

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
    a = feats_i[matches[:, 0]]
    b = feats_j[matches[:, 1]]
    logits = a @ b.T / temperature
    p = points_i[matches[:, 0]]
    near = torch.cdist(p, p) < safe_radius
    near.fill_diagonal_(False)
    logits = logits.masked_fill(near, float("-inf"))
    target = torch.arange(len(matches), device=logits.device)
    return 0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target))
