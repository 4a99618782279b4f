"""Weighted Procrustes (Kabsch with weights), batched and differentiable, and ``FitResult``.

Method (the paper's section 3.1, Geometric Fitting), in float64 whatever the input dtype:

* ``w_hat = w / (sum(w) + 1e-5)``;
* weighted means ``mu = sum(w p) / sum(w)`` (normalised exactly, so that ``t`` has no
  ``1e-5``-sized bias and noise-free data are recovered to rounding);
* both centred sets multiplied by ``w_hat``, ``H = sum_i w_hat_i^2 (p_i - mu_src)(q_i - mu_tgt)^T``
  (3x3);
* ``H = U S V^T``, ``R = V diag(1, 1, d) U^T`` with ``d = sign(det(V U^T))`` (never a
  reflection), ``t = mu_tgt - R mu_src``.

Degenerate input never raises; the result is always a proper rotation (``det R = +1``):

* all weights zero (or no points): the weights fall back to uniform ones (the limit of
  ``c * ones`` as ``c -> 0``; the fit is invariant to the scale of the weights);
* fewer than 3 points with non-zero weight, or collinear points (``rank H < 2``): the
  rotation about the degenerate axis is arbitrary (whatever the SVD returns) and the
  translation still maps the weighted mean onto the weighted mean; with no points at all
  the result is the identity.

:func:`weighted_procrustes` warns (``UserWarning``) in those cases unless
``warn_degenerate=False`` (the robust estimators pass False: their random subsets are
expected to be degenerate now and then). Gradients are not defined there (SVD with
repeated singular values).
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import torch

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.transforms import apply_transform, make_transform

#: Added to ``sum(w)`` in ``w_hat = w / (sum(w) + PROCRUSTES_EPS)`` (the paper's section 3.1).
PROCRUSTES_EPS = 1e-5


class FitResult(NamedTuple):
    """Outcome of a robust fit (:func:`randomized_procrustes`, :func:`ransac`).

    Attributes:
        T_tgt_src: ``(4, 4)`` transform (dtype of the input points, on their device).
        inlier_mask: ``(K,)`` bool, ``|T p_i - q_i| < inlier_threshold`` under ``T_tgt_src``;
            ``None`` when no threshold was given.
        num_inliers: ``inlier_mask.sum()``; ``None`` when no threshold was given.
        score: the estimator's cost of ``T_tgt_src``, lower is better: randomized
            Procrustes' ``mean_i(w_i |R p_i + t - q_i|)``; RANSAC's inlier RMSE
            (``inf`` with no inliers).
        iterations: candidate transforms drawn (subsets or minimal sets).
    """

    T_tgt_src: torch.Tensor
    inlier_mask: torch.Tensor | None
    num_inliers: int | None
    score: float
    iterations: int


def _check_correspondence_shapes(
    points_src: torch.Tensor, points_tgt: torch.Tensor, weight: torch.Tensor | None
) -> None:
    for name, pts in (("points_src", points_src), ("points_tgt", points_tgt)):
        if pts.ndim < 2 or pts.shape[-1] != 3:
            raise ShapeError(f"{name} must have shape (..., K, 3), got {tuple(pts.shape)}")
    if points_src.shape[-2] != points_tgt.shape[-2]:
        raise ShapeError(
            f"points_src and points_tgt must have the same K, got {tuple(points_src.shape)} "
            f"and {tuple(points_tgt.shape)}"
        )
    if weight is not None and (weight.ndim < 1 or weight.shape[-1] != points_src.shape[-2]):
        raise ShapeError(
            f"weight must have shape (..., K) with K = {points_src.shape[-2]}, "
            f"got {tuple(weight.shape)}"
        )


def _result_dtype(points_src: torch.Tensor, points_tgt: torch.Tensor) -> torch.dtype:
    dtype = torch.promote_types(points_src.dtype, points_tgt.dtype)
    return dtype if dtype.is_floating_point else torch.float64


def _degenerate(all_zero: torch.Tensor, S: torch.Tensor) -> bool:
    """All weights zero, or ``rank H < 2`` (fewer than 3 weighted points, collinear points)."""
    tol = 100.0 * torch.finfo(S.dtype).eps
    rank_deficient = S[..., 1] <= tol * S[..., 0]  # also true when S == 0
    return bool(all_zero.any() | rank_deficient.any())


def weighted_procrustes(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    weight: torch.Tensor | None = None,
    *,
    warn_degenerate: bool = True,
) -> torch.Tensor:
    """Weighted least-squares rigid transform, ``T_tgt_src`` with ``q ~ R p + t``.

    Objective: the rotation and translation that align the weighted, centred source points
    onto the target points (the paper's section 3.1; see the module docstring for the exact
    weighting and for degenerate inputs). Batched over leading dimensions (broadcast), and
    differentiable with respect to the points and the weights on non-degenerate inputs.

    Args:
        points_src: ``(..., K, 3)`` source points ``p``.
        points_tgt: ``(..., K, 3)`` target points ``q``.
        weight: ``(..., K)`` non-negative weights; ``None`` means all ones (Kabsch).
        warn_degenerate: warn when an element of the batch is degenerate (all weights zero,
            fewer than 3 weighted points, collinear points). Checking costs a device sync.

    Returns:
        ``(..., 4, 4)`` ``T_tgt_src`` in the points' dtype (float64 for integer points),
        always a proper rotation.

    Raises:
        ShapeError: shapes are not ``(..., K, 3)``, ``(..., K, 3)``, ``(..., K)``.
    """
    _check_correspondence_shapes(points_src, points_tgt, weight)
    out_dtype = _result_dtype(points_src, points_tgt)
    f64 = torch.float64
    p = points_src.to(f64)
    q = points_tgt.to(f64)
    w = p.new_ones(p.shape[:-1]) if weight is None else weight.to(f64)

    w_sum = w.sum(-1, keepdim=True)  # (..., 1)
    all_zero = w_sum <= 0
    w = torch.where(all_zero, torch.ones_like(w), w)  # uniform fallback
    w_sum = torch.where(all_zero, w.sum(-1, keepdim=True), w_sum)
    w_hat = w / (w_sum + PROCRUSTES_EPS)

    denom = w_sum.clamp_min(torch.finfo(f64).tiny).unsqueeze(-1)  # (..., 1, 1)
    mu_src = (w.unsqueeze(-1) * p).sum(-2, keepdim=True) / denom  # (..., 1, 3)
    mu_tgt = (w.unsqueeze(-1) * q).sum(-2, keepdim=True) / denom
    src_c = (p - mu_src) * w_hat.unsqueeze(-1)
    tgt_c = (q - mu_tgt) * w_hat.unsqueeze(-1)
    H = src_c.transpose(-1, -2) @ tgt_c  # (..., 3, 3), sum_i p_c q_c^T

    U, S, Vh = torch.linalg.svd(H, full_matrices=False)
    V = Vh.transpose(-1, -2)
    Ut = U.transpose(-1, -2)
    det = torch.linalg.det(V @ Ut).detach()
    flip = torch.ones(*det.shape, 3, dtype=f64, device=det.device)
    flip[..., 2] = torch.where(det < 0, -1.0, 1.0)
    R = (V * flip.unsqueeze(-2)) @ Ut
    t = mu_tgt.squeeze(-2) - (R @ mu_src.transpose(-1, -2)).squeeze(-1)

    if warn_degenerate and _degenerate(all_zero, S.detach()):
        warnings.warn(
            "weighted_procrustes: degenerate input (all weights zero, fewer than 3 weighted "
            "points or collinear points); the rotation is not unique",
            UserWarning,
            stacklevel=2,
        )
    return make_transform(R, t).to(out_dtype)


def weighted_residuals(
    T_tgt_src: torch.Tensor, points_src: torch.Tensor, points_tgt: torch.Tensor
) -> torch.Tensor:
    """Residual norms ``r_i = |R p_i + t - q_i|`` (L2, not squared; the paper's section 3.1,
    Registration Loss).

    Args:
        T_tgt_src: ``(..., 4, 4)`` transform.
        points_src: ``(..., K, 3)`` source points ``p``.
        points_tgt: ``(..., K, 3)`` target points ``q``.

    Returns:
        ``(..., K)`` residuals in the points' common dtype (differentiable).

    Raises:
        ShapeError: wrong shapes.
    """
    _check_correspondence_shapes(points_src, points_tgt, None)
    dtype = _result_dtype(points_src, points_tgt)
    moved = apply_transform(T_tgt_src.to(dtype), points_src.to(dtype))
    return torch.linalg.vector_norm(moved - points_tgt.to(dtype), dim=-1)
