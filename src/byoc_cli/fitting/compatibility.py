"""Second-order spatial compatibility: a robust fit for correspondences with few inliers.

After Chen et al., "SC²-PCR: A Second Order Spatial Compatibility for Efficient and Robust
Point Cloud Registration" (CVPR 2022). A rigid motion keeps distances, so two inlier
correspondences ``i, j`` have ``|p_i - p_j| ~ |q_i - q_j|``; RANSAC draws triplets hoping for
three inliers (``inlier_ratio**3`` of its draws at best), this estimator instead ranks the
correspondences by how many others agree with them and fits only around the best agreed ones.
On ``K`` correspondences ``p, q (K, 3)`` (one pair of clouds; no batch):

1. **cap**: the ``M = min(K, max_correspondences)`` correspondences of highest weight (the
   ratio-test weight; ties and ``weight=None`` go to the lower index) enter the ``M x M``
   matrices below; the others are still scored in step 6 and can be inliers of the result;
2. **first order**: ``H_ij = 1`` when ``| |p_i - p_j| - |q_i - q_j| | < sigma``, else 0, with
   ``sigma = compatibility_factor * inlier_threshold`` (hard, as SC²-PCR);
3. **second order**: ``SC2 = H * (H @ H)``: for a compatible pair, how many correspondences are
   compatible with both. Two inliers share every other inlier, an inlier and an outlier (or two
   outliers) only the chance ones, so ``SC2`` parts inliers from outliers where ``H`` alone does
   not (at 3 % inliers among 2000, about 60 shared against 5);
4. **seeds**: each correspondence's score is its entry in the leading eigenvector of ``SC2``
   (power iteration from ones); a correspondence is a seed candidate when no correspondence
   whose source point lies within ``nms_factor * inlier_threshold`` of its own scores higher
   (non-maximum suppression, so seeds spread over the scene), and the ``ceil(seed_ratio * M)``
   best candidates are the seeds;
5. **consensus and fit** per seed, all seeds in one batch: the ``k1`` correspondences of
   highest ``SC2`` with the seed, then among them the ``k2`` of highest second-order
   compatibility with the seed inside that set (SC²-PCR's two-stage sampling); a weighted
   Procrustes on those ``k2`` (:func:`~byoc_cli.fitting.procrustes.weighted_procrustes`)
   weighted by the leading eigenvector of their soft second-order compatibility ``C * (C @ C)``,
   ``C = max(0, 1 - d^2 / sigma^2)`` (``d`` the length difference), members not compatible
   with the seed weighted 0 and those below :data:`WEIGHT_FLOOR` of the set's largest weight too
   (an outlier that agrees with the seed but with few of the others gets a small weight, and a
   small weight on a far point still tilts the fit);
6. **selection**: every candidate refitted once on its inliers among all ``K``
   correspondences (``r_k = |R p_k + t - q_k| < inlier_threshold``; the consensus set of a seed
   can hold an outlier compatible with it, which tilts the fit), then the one with the highest
   truncated score ``sum_k max(0, 1 - r_k / inlier_threshold)`` (the first on ties);
7. **refit** on its inliers (``r_k < inlier_threshold``), as :func:`~byoc_cli.fitting.ransac`
   does (:func:`~byoc_cli.fitting.ransac.refit_on_inliers`).

Memory: ``H`` and ``SC2`` are float32 ``M x M`` and the source neighbourhoods bool ``M x M``
(``9 M^2`` bytes: 9 MB at the default cap of 1000, 36 MB at 2000, 225 MB at 5000); distances
are computed in row chunks of :data:`CHUNK_ELEMENTS`, and the candidates are scored in chunks
of :data:`SCORE_ELEMENTS` residuals. Time: the product ``H @ H`` is ``2 M^3`` flops (0.03 s at
``M = 1000``, 0.2 s at 2000, 3 s or more at 5000 on one core). The cap of 1000 is measured:
on the development pairs of docs/low-overlap.md the fit took 0.1-0.2 s a pair against 0.45-0.65 s
at 2000 and registered the same pairs within one (benchmarks/low_overlap_estimators.py).

No random draw: the same input gives the same bits. ``generator`` is accepted (and not drawn
from) so that every estimator takes the same arguments.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from byoc_cli.errors import RegistrationError, ShapeError
from byoc_cli.fitting.procrustes import (
    FitResult,
    _check_correspondence_shapes,
    _result_dtype,
    weighted_procrustes,
)
from byoc_cli.fitting.ransac import refit_on_inliers

#: Elements of the row chunks of pairwise distances (``chunk x M``; 32 MB in float64).
CHUNK_ELEMENTS = 2**22
#: Residuals ``candidates x K`` scored at once (their ``(c, K, 3)`` temporaries: 12 MB each).
SCORE_ELEMENTS = 2**19
#: Consensus members weighted below this share of their set's largest weight are left out
#: of its fit (weight 0).
WEIGHT_FLOOR = 0.5
#: Power iterations for the leading eigenvectors (global and per consensus set).
POWER_ITERATIONS = 30


@dataclass(frozen=True)
class CompatibilityTuning:
    """How :func:`spatial_compatibility` ranks and expands (its keyword arguments).

    Attributes:
        max_correspondences: the cap ``M`` on the correspondences in the ``M x M`` matrices
            (the highest weights; memory ``8 M^2`` bytes, time ``2 M^3`` flops).
        compatibility_factor: ``sigma``, the largest length difference of a compatible pair,
            as a multiple of the inlier threshold.
        seed_ratio: seeds as a share of ``M`` (at least one).
        nms_factor: radius of the non-maximum suppression of seeds around their source
            points, as a multiple of the inlier threshold.
        k1: first-stage consensus size (the highest ``SC2`` with the seed).
        k2: second-stage consensus size (``k2 <= k1``), the correspondences each candidate is
            fitted on.
        refit_iterations: Procrustes refits on the inliers of the chosen candidate (>= 0).
    """

    max_correspondences: int = 1000
    compatibility_factor: float = 1.0
    seed_ratio: float = 0.1
    nms_factor: float = 1.0
    k1: int = 30
    k2: int = 20
    refit_iterations: int = 2

    def check(self) -> None:
        """Raise ``ValueError`` naming the first value out of range."""
        if self.max_correspondences < 3:
            raise ValueError(f"max_correspondences must be >= 3, got {self.max_correspondences}")
        if not self.compatibility_factor > 0 or not self.nms_factor >= 0:
            raise ValueError(
                "compatibility_factor must be > 0 and nms_factor >= 0, got "
                f"{self.compatibility_factor}, {self.nms_factor}"
            )
        if not 0 < self.seed_ratio <= 1:
            raise ValueError(f"seed_ratio must be in (0, 1], got {self.seed_ratio}")
        if not 3 <= self.k2 <= self.k1:
            raise ValueError(f"k1 and k2 must satisfy 3 <= k2 <= k1, got {self.k1}, {self.k2}")
        if self.refit_iterations < 0:
            raise ValueError(f"refit_iterations must be >= 0, got {self.refit_iterations}")


def spatial_compatibility(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    inlier_threshold: float,
    weight: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    **tuning: Any,
) -> FitResult:
    """``T_tgt_src`` from the second-order spatial compatibility of the correspondences.

    Objective: the transform, among one weighted Procrustes fit per seed on its consensus set,
    with the highest truncated score ``sum_k max(0, 1 - |R p_k + t - q_k| / inlier_threshold)``,
    refitted on its inliers (the steps and their costs: the module docstring).

    Args:
        points_src: ``(K, 3)`` source points ``p`` of the correspondences.
        points_tgt: ``(K, 3)`` target points ``q``.
        inlier_threshold: residual distance below which a correspondence is an inlier (> 0);
            also the unit of the compatibility and suppression radii.
        weight: ``(K,)`` non-negative weights (the ratio test's): which correspondences
            enter the matrices when ``K`` exceeds the cap; ``None``: the first ones.
        generator: not drawn from (the estimator is deterministic); accepted so that every
            estimator takes the same arguments.
        tuning: the fields of :class:`CompatibilityTuning`.

    Returns:
        :class:`~byoc_cli.fitting.procrustes.FitResult`: ``score`` the inlier RMSE (``inf``
        with no inliers), ``iterations`` the candidates fitted (the seeds).

    Raises:
        ShapeError: shapes are not ``(K, 3)``, ``(K, 3)``, ``(K,)``.
        RegistrationError: fewer than 3 correspondences.
        ValueError: an argument is out of range.
        TypeError: an unknown keyword.
    """
    del generator  # deterministic; see the docstring
    tuned = CompatibilityTuning(**tuning)
    tuned.check()
    _check_correspondence_shapes(points_src, points_tgt, weight)
    if points_src.ndim != 2 or points_tgt.ndim != 2 or (weight is not None and weight.ndim != 1):
        raise ShapeError("spatial_compatibility takes (K, 3), (K, 3) and (K,) tensors")
    if not inlier_threshold > 0:
        raise ValueError(f"inlier_threshold must be > 0, got {inlier_threshold}")
    num = points_src.shape[0]
    if num < 3:
        raise RegistrationError(
            f"spatial compatibility needs at least 3 correspondences, got {num}"
        )

    out_dtype = _result_dtype(points_src, points_tgt)
    device = points_src.device
    p = points_src.detach().to(torch.float64)
    q = points_tgt.detach().to(device=device, dtype=torch.float64)
    threshold = float(inlier_threshold)
    sigma = tuned.compatibility_factor * threshold

    kept = _cap(num, weight, tuned.max_correspondences, device)
    pk, qk = p[kept], q[kept]
    H, near = _pairwise(pk, qk, sigma, tuned.nms_factor * threshold)
    SC2 = (H @ H).mul_(H)  # (M, M) second-order compatibility
    seeds = _seeds(near, _leading_eigenvector(SC2), tuned.seed_ratio)
    del near
    members, member_weight = _consensus(H, SC2, seeds, pk, qk, sigma, tuned.k1, tuned.k2)
    T = weighted_procrustes(pk[members], qk[members], member_weight, warn_degenerate=False)
    best = _select(T, p, q, threshold)

    T, mask, residual = refit_on_inliers(p, q, best, threshold, tuned.refit_iterations)
    num_inliers = int(mask.sum())
    rmse = float(residual[mask].square().mean().sqrt()) if num_inliers else math.inf
    return FitResult(
        T_tgt_src=T.to(out_dtype),
        inlier_mask=mask,
        num_inliers=num_inliers,
        score=rmse,
        iterations=int(seeds.shape[0]),
    )


def _cap(num: int, weight: torch.Tensor | None, cap: int, device) -> torch.Tensor:
    """``(M,)`` int64 indices of the correspondences that enter the matrices: all when
    ``num <= cap``, else the ``cap`` of highest weight (ties and no weights: lower index)."""
    if num <= cap or weight is None:
        return torch.arange(min(num, cap), device=device)
    order = torch.sort(weight.detach().to(torch.float64), descending=True, stable=True).indices
    return order[:cap].sort().values


def _pairwise(
    p: torch.Tensor, q: torch.Tensor, sigma: float, radius: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Hard compatibility and source neighbourhoods of the correspondences ``p, q (M, 3)``.

    Returns:
        ``H (M, M)`` float32: 1 where the length difference ``| |p_i - p_j| - |q_i - q_j| |``
        is below ``sigma`` (the diagonal is 1); ``near (M, M)`` bool: ``|p_i - p_j| <=
        radius``. Distances in float64 on centred points (the matrix-product form of
        ``torch.cdist`` keeps about ``1e-8`` of the clouds' extent), in row chunks.
    """
    num = p.shape[0]
    p = p - p.mean(0)
    q = q - q.mean(0)
    H = p.new_empty((num, num), dtype=torch.float32)
    near = torch.empty((num, num), dtype=torch.bool, device=p.device)
    step = max(1, CHUNK_ELEMENTS // num)
    for start in range(0, num, step):
        rows = slice(start, start + step)
        d_src = torch.cdist(p[rows], p)
        near[rows] = d_src <= radius
        H[rows] = ((d_src - torch.cdist(q[rows], q)).abs_() < sigma).to(torch.float32)
    return H, near


def _leading_eigenvector(A: torch.Tensor, iterations: int = POWER_ITERATIONS) -> torch.Tensor:
    """Leading eigenvector of the non-negative symmetric ``A (..., n, n)`` by power iteration
    from ones, ``(..., n)``, non-negative, unit norm (zero rows give zero entries)."""
    v = A.new_ones(A.shape[:-1])
    for _ in range(iterations):
        v = (A @ v.unsqueeze(-1)).squeeze(-1)
        v = v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-30)
    return v


def _seeds(near: torch.Tensor, score: torch.Tensor, ratio: float) -> torch.Tensor:
    """``(S,)`` int64 seeds: the correspondences whose ``score (M,)`` is the highest among
    their neighbours (``near (M, M)`` bool, the diagonal true), the ``ceil(ratio * M)`` best of
    them (descending score, ties to the lower index)."""
    num = score.shape[0]
    local_max = torch.empty(num, dtype=torch.bool, device=score.device)
    step = max(1, CHUNK_ELEMENTS // num)
    for start in range(0, num, step):
        rows = slice(start, start + step)
        top = torch.where(near[rows], score[None, :], -math.inf).amax(dim=1)
        local_max[rows] = score[rows] >= top
    candidates = local_max.nonzero().squeeze(1)
    order = torch.sort(score[candidates], descending=True, stable=True).indices
    return candidates[order[: max(1, math.ceil(ratio * num))]]


def _consensus(H, SC2, seeds, p, q, sigma: float, k1: int, k2: int):
    """The consensus set of every seed and the weights of its fit.

    Args:
        H, SC2: ``(M, M)`` first- and second-order compatibility.
        seeds: ``(S,)`` int64.
        p, q: ``(M, 3)`` float64 correspondences.

    Returns:
        ``members (S, k2)`` int64 (the seed first), ``weight (S, k2)`` float64: the leading
        eigenvector of the members' soft second-order compatibility, 0 for members incompatible
        with the seed or below :data:`WEIGHT_FLOOR` of the largest.
    """
    num = H.shape[0]
    k1, k2 = min(k1, num), min(k2, num)
    rows = torch.arange(len(seeds), device=seeds.device)
    # stage 1: the k1 highest SC2 with the seed (the seed itself first)
    first = SC2[seeds].clone()
    first[rows, seeds] = math.inf
    near = torch.sort(first, dim=1, descending=True, stable=True).indices[:, :k1]  # (S, k1)
    # stage 2: second-order compatibility with the seed within those k1
    local = H[near[:, :, None], near[:, None, :]]  # (S, k1, k1)
    local_sc2 = (local @ local).mul_(local)[:, 0, :]  # the seed's row, (S, k1)
    local_sc2[:, 0] = math.inf
    pick = torch.sort(local_sc2, dim=1, descending=True, stable=True).indices[:, :k2]
    members = near.gather(1, pick)  # (S, k2)
    # local spectral weights on the soft second-order compatibility of the members
    diff = torch.cdist(p[members], p[members]) - torch.cdist(q[members], q[members])
    soft = (1.0 - diff.square() / sigma**2).clamp_min(0.0)
    soft_sc2 = (soft @ soft).mul_(soft)
    weight = _leading_eigenvector(soft_sc2) * H[seeds[:, None], members].to(torch.float64)
    # a far outlier with a tenth of an inlier's weight still tilts a least-squares fit
    weight[weight < WEIGHT_FLOOR * weight.amax(dim=1, keepdim=True)] = 0.0
    return members, weight


def _select(T: torch.Tensor, p: torch.Tensor, q: torch.Tensor, threshold: float) -> torch.Tensor:
    """The best candidate of ``T (S, 4, 4)`` on the correspondences ``p, q (K, 3)``, ``(4, 4)``.

    Each candidate is first refitted (unit-weight Procrustes) on its inliers among all ``K``
    (``r_k < threshold``; a candidate with fewer than 3 stays as it is), then scored by
    ``sum_k max(0, 1 - r_k / threshold)``; the highest score wins (the first on ties). In
    chunks of :data:`SCORE_ELEMENTS` residuals.
    """
    step = max(1, SCORE_ELEMENTS // p.shape[0])
    refits, scores = [], []
    for start in range(0, T.shape[0], step):
        T0 = T[start : start + step]
        inlier = (_residuals(T0, p, q) < threshold).to(p.dtype)  # (c, K)
        T1 = weighted_procrustes(
            p.expand(len(T0), -1, -1), q.expand(len(T0), -1, -1), inlier, warn_degenerate=False
        )
        T1 = torch.where((inlier.sum(1) >= 3)[:, None, None], T1, T0)
        refits.append(T1)
        scores.append((1.0 - _residuals(T1, p, q) / threshold).clamp_min_(0.0).sum(1))
    return torch.cat(refits)[int(torch.argmax(torch.cat(scores)))]


def _residuals(T: torch.Tensor, p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """``(c, K)`` residuals ``|R p_k + t - q_k|`` of candidates ``T (c, 4, 4)``."""
    moved = p @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]  # (c, K, 3)
    return torch.linalg.vector_norm(moved - q, dim=-1)
