"""Correspondence RANSAC with batched minimal sets and adaptive stopping."""

from __future__ import annotations

import math
import warnings
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
from byoc_cli.fitting.randomized import default_generator
from byoc_cli.limits import CONFIDENCE, MAX_ITERATIONS

#: Upper bound on ``batch * K`` squared residuals scored at once (16 MB in float32, 32 MB in
#: float64).
SCORE_BUDGET = 2**22


def required_iterations(inlier_ratio: float, confidence: float, sample_size: int = 3) -> float:
    """Standard RANSAC bound ``log(1 - confidence) / log(1 - inlier_ratio ** sample_size)``.

    Returns ``inf`` when no finite number of draws reaches the confidence (no inliers, or
    ``confidence == 1``) and 0 when every correspondence is an inlier.
    """
    good = inlier_ratio**sample_size
    if good >= 1.0:
        return 0.0
    if good <= 0.0 or confidence >= 1.0:
        return math.inf
    return math.log1p(-confidence) / math.log1p(-good)


def _sample_triplets(num: int, batch: int, generator: torch.Generator) -> torch.Tensor:
    """``(batch, 3)`` int64 triplets of distinct indices in ``[0, num)``, uniform."""
    kw = {"generator": generator, "device": generator.device}
    a = torch.randint(num, (batch,), **kw)
    b = torch.randint(num - 1, (batch,), **kw)
    c = torch.randint(num - 2, (batch,), **kw)
    b = b + (b >= a).long()
    lo = torch.minimum(a, b)
    hi = torch.maximum(a, b)
    c = c + (c >= lo).long()
    c = c + (c >= hi).long()
    return torch.stack([a, b, c], dim=1)


def _edge_lengths(points: torch.Tensor) -> torch.Tensor:
    """``(B, 3, 3)`` triangles -> ``(B, 3)`` edge lengths (01, 12, 20)."""
    return torch.linalg.vector_norm(points - points.roll(-1, dims=1), dim=-1)


class _CandidateScorer:
    """Inlier counts and squared inlier residual sums of many candidate transforms at once.

    With centred points ``p' = p - c_p``, ``q' = q - c_q`` and ``t' = R c_p + t - c_q``,
    ``|R p + t - q|^2 = |p'|^2 + |q'|^2 + |t'|^2 + 2 p'.(R^T t') - 2 <R, q' p'^T> - 2 q'.t'``,
    so the ``(B, K)`` squared residuals are one GEMM of ``(B, 17)`` candidate rows with
    ``(17, K)`` correspondence columns. The GEMM runs in float32 when the rounding error
    of that expansion (about ``1e-6 * scale^2``) stays below 1 % of ``threshold^2``, in
    float64 otherwise; the final inlier sets are always recomputed directly in float64.
    """

    def __init__(self, p: torch.Tensor, q: torch.Tensor, threshold: float) -> None:
        self.c_src = p.mean(0)
        self.c_tgt = q.mean(0)
        pc = p - self.c_src
        qc = q - self.c_tgt
        self.thr2 = threshold**2
        self.num = p.shape[0]
        scale2 = float(pc.square().sum(-1).max() + qc.square().sum(-1).max())
        self.dtype = torch.float32 if 1e-6 * scale2 <= 1e-2 * self.thr2 else torch.float64
        self.feat = (
            torch.cat(
                [
                    pc,
                    (qc.unsqueeze(2) * pc.unsqueeze(1)).reshape(-1, 9),
                    qc,
                    pc.square().sum(-1, keepdim=True) + qc.square().sum(-1, keepdim=True),
                    torch.ones_like(pc[:, :1]),
                ],
                dim=1,
            )
            .T.contiguous()
            .to(self.dtype)
        )  # (17, K)

    def __call__(self, T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, 4, 4)`` float64 candidates -> ``(B,)`` inlier counts, ``(B,)`` error sums."""
        R = T[:, :3, :3]
        t_c = (R @ self.c_src) + T[:, :3, 3] - self.c_tgt  # (B, 3)
        coef = torch.cat(
            [
                2.0 * (R.transpose(1, 2) @ t_c.unsqueeze(-1)).squeeze(-1),
                -2.0 * R.reshape(-1, 9),
                -2.0 * t_c,
                torch.ones_like(t_c[:, :1]),
                t_c.square().sum(-1, keepdim=True),
            ],
            dim=1,
        ).to(self.dtype)  # (B, 17)
        r2 = coef @ self.feat  # (B, K) squared residuals
        # 1.0 for an inlier, 0.0 otherwise (a float mask sums faster than a bool one); the
        # sum is exact, K < 2**24
        hit = torch.lt(r2, self.thr2, out=torch.empty_like(r2))
        count = hit.sum(-1).long()
        # sum of squared inlier residuals = sum(min(r2, thr2)) - thr2 * (K - count)
        trunc = r2.clamp_max_(self.thr2).sum(-1).double()
        return count, trunc - self.thr2 * (self.num - count)


def refit_on_inliers(
    p: torch.Tensor, q: torch.Tensor, T: torch.Tensor, threshold: float, iterations: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Refit unit-weight Procrustes on the inliers of ``T``, up to ``iterations`` times.

    A refit is kept only if it loses no inlier; the loop stops early when fewer than 3
    inliers are left or the inlier set no longer changes.

    Args:
        p, q: ``(K, 3)`` float64 correspondences.
        T: ``(4, 4)`` float64 starting transform.
        threshold: inlier distance (``|T p_i - q_i| < threshold``).
        iterations: most refits (>= 0).

    Returns:
        ``(T (4, 4), inlier_mask (K,), residual (K,))`` of the transform kept.
    """

    def inliers_of(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r = torch.linalg.vector_norm(p @ T[:3, :3].T + T[:3, 3] - q, dim=-1)
        return r < threshold, r

    mask, residual = inliers_of(T)
    for _ in range(iterations):
        count = int(mask.sum())
        if count < 3:
            break
        T_new = weighted_procrustes(p[mask], q[mask], None, warn_degenerate=False)
        mask_new, residual_new = inliers_of(T_new)
        if int(mask_new.sum()) < count:
            break
        same = torch.equal(mask_new, mask)
        T, mask, residual = T_new, mask_new, residual_new
        if same:
            break
    return T, mask, residual


@dataclass(frozen=True)
class RansacTuning:
    """How :func:`ransac` draws and refits (its keyword arguments besides the limits).

    Attributes:
        batch_size: minimal sets per batch (capped so that ``batch * K`` stays within
            :data:`SCORE_BUDGET`).
        edge_length_ratio: similarity in ``(0, 1]`` for the edge-length check; ``None``
            turns it off.
        refit_iterations: Procrustes refits on the inliers (>= 0).
    """

    batch_size: int = 1024
    edge_length_ratio: float | None = 0.9
    refit_iterations: int = 2


def ransac(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    inlier_threshold: float,
    max_iterations: int = MAX_ITERATIONS,
    confidence: float = CONFIDENCE,
    generator: torch.Generator | None = None,
    **tuning: Any,
) -> FitResult:
    """Correspondence RANSAC: ``T_tgt_src`` with the most inliers ``|T p_i - q_i| < threshold``.

    Objective: draw minimal sets of 3 distinct correspondences in batches (one tensor of
    ``batch_size`` sets at a time), optionally reject sets whose edge lengths differ between
    the clouds by more than ``edge_length_ratio`` (Open3D's
    ``CorrespondenceCheckerBasedOnEdgeLength``), fit Kabsch on each (unit-weight
    :func:`weighted_procrustes`), count the inliers of every candidate, keep the best (most
    inliers; ties go to the lower sum of squared inlier residuals, then to the earlier
    draw). Stops once ``required_iterations(best_inliers / K, confidence)`` draws are done or
    ``max_iterations`` is reached (checked after each batch). Finally refits Procrustes on
    the inliers of the best model, up to ``refit_iterations`` times, keeping a refit only if
    it does not lose inliers. Same generator state and arguments -> bit-identical result.

    Args:
        points_src: ``(K, 3)`` source points ``p`` of the correspondences.
        points_tgt: ``(K, 3)`` target points ``q``.
        inlier_threshold: residual distance below which a correspondence is an inlier (> 0).
        max_iterations: most minimal sets drawn (>= 1).
        confidence: probability in ``(0, 1]`` of having drawn one all-inlier set.
        generator: source of the minimal sets; indices are drawn on its device. ``None``
            uses a fresh generator seeded with 0.
        tuning: ``batch_size``, ``edge_length_ratio``, ``refit_iterations``: see
            :class:`RansacTuning`.

    Returns:
        :class:`FitResult`; ``score`` is the inlier RMSE, ``iterations`` the minimal sets
        drawn (including rejected ones). If every minimal set was rejected by the
        edge-length check the identity is returned, with a warning.

    Raises:
        ShapeError: shapes are not ``(K, 3)``.
        RegistrationError: fewer than 3 correspondences.
        ValueError: an argument is out of range.
        TypeError: an unknown keyword.
    """
    tuned = RansacTuning(**tuning)
    batch_size, edge_length_ratio = tuned.batch_size, tuned.edge_length_ratio
    refit_iterations = tuned.refit_iterations
    _check_correspondence_shapes(points_src, points_tgt, None)
    if points_src.ndim != 2 or points_tgt.ndim != 2:
        raise ShapeError("ransac takes (K, 3) and (K, 3) tensors")
    if not inlier_threshold > 0:
        raise ValueError(f"inlier_threshold must be > 0, got {inlier_threshold}")
    if max_iterations < 1 or batch_size < 1 or refit_iterations < 0:
        raise ValueError("max_iterations and batch_size must be >= 1, refit_iterations >= 0")
    if not 0 < confidence <= 1:
        raise ValueError(f"confidence must be in (0, 1], got {confidence}")
    if edge_length_ratio is not None and not 0 < edge_length_ratio <= 1:
        raise ValueError(f"edge_length_ratio must be in (0, 1], got {edge_length_ratio}")
    num = points_src.shape[0]
    if num < 3:
        raise RegistrationError(f"RANSAC needs at least 3 correspondences, got {num}")

    out_dtype = _result_dtype(points_src, points_tgt)
    device = points_src.device
    p = points_src.detach().to(torch.float64)
    q = points_tgt.detach().to(device=device, dtype=torch.float64)
    generator = generator or default_generator(device)

    scorer = _CandidateScorer(p, q, float(inlier_threshold))
    batch_cap = max(1, min(batch_size, SCORE_BUDGET // num))

    best_T = None
    best_count = -1
    best_err = math.inf
    iterations = 0
    needed = math.inf
    while iterations < min(needed, max_iterations):
        batch = min(batch_cap, max_iterations - iterations)
        idx = _sample_triplets(num, batch, generator).to(device)
        iterations += batch
        sp, sq = p[idx], q[idx]  # (batch, 3, 3)
        if edge_length_ratio is not None:
            ds, dt = _edge_lengths(sp), _edge_lengths(sq)
            ok = ((ds >= edge_length_ratio * dt) & (dt >= edge_length_ratio * ds)).all(-1)
            sp, sq = sp[ok], sq[ok]
            if sp.shape[0] == 0:
                continue
        T = weighted_procrustes(sp, sq, None, warn_degenerate=False)  # (b, 4, 4) float64
        count, err = scorer(T)
        top = count.max()
        j = int(torch.argmin(torch.where(count == top, err, math.inf)))
        c_j, e_j = int(count[j]), float(err[j])
        if c_j > best_count or (c_j == best_count and e_j < best_err):
            best_T, best_count, best_err = T[j], c_j, e_j
            needed = required_iterations(best_count / num, confidence)

    if best_T is None:
        warnings.warn(
            "ransac: every minimal set failed the edge-length check; returning the identity",
            UserWarning,
            stacklevel=2,
        )
        best_T = torch.eye(4, dtype=torch.float64, device=device)

    T, mask, residual = refit_on_inliers(p, q, best_T, inlier_threshold, refit_iterations)
    num_inliers = int(mask.sum())
    score = float(residual[mask].square().mean().sqrt()) if num_inliers else math.inf
    return FitResult(
        T_tgt_src=T.to(out_dtype),
        inlier_mask=mask,
        num_inliers=num_inliers,
        score=score,
        iterations=iterations,
    )
