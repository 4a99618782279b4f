"""Randomized weighted Procrustes: BYOC's test-time estimator (the paper's section 3.1, Geometric
Fitting; docs/registering.md)."""

from __future__ import annotations

import torch

from byoc_cli.errors import RegistrationError, ShapeError
from byoc_cli.fitting.procrustes import (
    FitResult,
    _check_correspondence_shapes,
    _result_dtype,
    weighted_procrustes,
)
from byoc_cli.limits import NUM_SUBSETS, SUBSET_SIZE


def default_generator(device: torch.device | str = "cpu") -> torch.Generator:
    """The generator used when none is given: seeded with 0 (never the global RNG)."""
    return torch.Generator(device=device).manual_seed(0)


def randomized_procrustes(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    weight: torch.Tensor | None = None,
    num_subsets: int = NUM_SUBSETS,
    subset_size: int = SUBSET_SIZE,
    generator: torch.Generator | None = None,
    inlier_threshold: float | None = None,
) -> FitResult:
    """Best of ``num_subsets`` weighted Procrustes fits on random subsets.

    Objective: draw ``num_subsets`` subsets of ``subset_size`` correspondences uniformly with
    replacement (one ``torch.randint`` of shape ``(num_subsets, subset_size)``), fit a
    weighted Procrustes on each with the subset's weights (all in one batch), score every
    candidate by ``mean_i(w_i * |R p_i + t - q_i|)`` over all ``K`` correspondences with the
    raw weights, and return the candidate with the lowest score (the first one on ties).
    The same generator state gives a bit-identical result.

    Args:
        points_src: ``(K, 3)`` source points ``p`` of the correspondences.
        points_tgt: ``(K, 3)`` target points ``q``.
        weight: ``(K,)`` non-negative weights (``None``: all ones).
        num_subsets: candidates (>= 1); 100 in the paper.
        subset_size: correspondences per subset (>= 1); 20 in the paper (0.05 x 400).
        generator: source of the subsets; indices are drawn on its device. ``None`` uses a
            fresh generator seeded with 0.
        inlier_threshold: if given, ``inlier_mask`` marks residuals below it.

    Returns:
        :class:`FitResult` with ``iterations = num_subsets`` and ``score`` the weighted mean
        residual of the returned transform.

    Raises:
        ShapeError: shapes are not ``(K, 3)``, ``(K, 3)``, ``(K,)``.
        RegistrationError: fewer than 3 correspondences.
        ValueError: ``num_subsets`` or ``subset_size`` < 1, or a negative threshold.
    """
    _check_correspondence_shapes(points_src, points_tgt, weight)
    if points_src.ndim != 2 or points_tgt.ndim != 2 or (weight is not None and weight.ndim != 1):
        raise ShapeError("randomized_procrustes takes (K, 3), (K, 3) and (K,) tensors")
    if num_subsets < 1 or subset_size < 1:
        raise ValueError(
            f"num_subsets and subset_size must be >= 1, got {num_subsets}, {subset_size}"
        )
    if inlier_threshold is not None and inlier_threshold < 0:
        raise ValueError(f"inlier_threshold must be >= 0, got {inlier_threshold}")
    num = points_src.shape[0]
    if num < 3:
        raise RegistrationError(
            f"randomized Procrustes needs at least 3 correspondences, got {num}"
        )

    out_dtype = _result_dtype(points_src, points_tgt)
    device = points_src.device
    p = points_src.to(torch.float64)
    q = points_tgt.to(device=device, dtype=torch.float64)
    w = p.new_ones(num) if weight is None else weight.to(device=device, dtype=torch.float64)
    generator = generator or default_generator(device)

    subsets = torch.randint(
        num, (num_subsets, subset_size), generator=generator, device=generator.device
    ).to(device)
    T = weighted_procrustes(p[subsets], q[subsets], w[subsets], warn_degenerate=False)
    residual = torch.linalg.vector_norm(
        p @ T[:, :3, :3].transpose(-1, -2) + T[:, None, :3, 3] - q, dim=-1
    )  # (num_subsets, K)
    scores = (w * residual).mean(-1)
    best = int(torch.argmin(scores))

    mask = None
    num_inliers = None
    if inlier_threshold is not None:
        mask = residual[best] < inlier_threshold
        num_inliers = int(mask.sum())
    return FitResult(
        T_tgt_src=T[best].to(out_dtype),
        inlier_mask=mask,
        num_inliers=num_inliers,
        score=float(scores[best]),
        iterations=num_subsets,
    )
