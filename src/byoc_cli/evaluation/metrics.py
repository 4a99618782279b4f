"""Evaluation metrics: feature-match recall, inlier ratios, registration RMSE, pose errors, chamfer.

Every function works on one pair (or on per-pair values) and knows nothing of files or
methods. Transforms are ``T_tgt_src`` (4x4, column vectors, ``x_tgt = R x_src + t``).

Protocols (the paper's sections 4.1 and 4.2, docs/evaluation.md; the names are those written
in reports):

* ``fmr``: feature-match recall. A pair's *inlier ratio* is the share of feature nearest
  neighbours whose points land within ``tau1`` of each other under the ground truth; the pair
  is *recalled* when that share is at least ``tau2`` (FCGF's ``hit_ratio >= tau_2``).
  FCGF's matching: one direction, plain nearest neighbour (no mutual check), queried from
  the smaller of the two sampled point sets (:func:`nn_inlier_ratio`).
* ``fmr-fcgf``: recall per scene, then the mean and (population) standard deviation over
  scenes. ``fmr-pooled``: recall over all pairs at once (the BYOC research code).
* ``corr``: the same recall on the filtered correspondences (top-k ratio test per direction).
* ``rr-3dmatch``: official registration recall: RMSE from ``gt.info`` at most 0.2 m
  (:func:`registration_rmse`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.geometry import (
    apply_transform,
    correspondence_inlier_ratio,
    rotation_error_deg,
    translation_error,
)
from byoc_cli.matching import feature_knn

__all__ = [
    "CHAMFER_SCALE",
    "ErrorSummary",
    "MatchInliers",
    "RecallSummary",
    "accuracy_at",
    "chamfer_distance",
    "correspondence_inlier_ratio",
    "error_summary",
    "fused_chamfer",
    "nn_inlier_ratio",
    "pose_errors",
    "quaternion_from_rotation",
    "recall_by_group",
    "registration_rmse",
]

#: Chamfer values are squared distances in m^2 multiplied by this (reported in 1e-3 m^2).
CHAMFER_SCALE = 1000.0


class MatchInliers(NamedTuple):
    """Output of :func:`nn_inlier_ratio`.

    Attributes:
        inlier_ratio: share of matches within ``tau1`` (0 when there is no match).
        num_matches: matches examined (the size of the query set).
        num_inliers: matches within ``tau1``.
    """

    inlier_ratio: float
    num_matches: int
    num_inliers: int


class RecallSummary(NamedTuple):
    """Recall per group (scene) and over groups.

    Attributes:
        per_group: ``{group: (recall, num_pairs)}`` in first-seen order.
        mean: mean of the per-group recalls (FCGF protocol); NaN without groups.
        std: population standard deviation of the per-group recalls (``numpy.std``, as FCGF).
        pooled: recall over all pairs at once (BYOC protocol); NaN without pairs.
        num_pairs: pairs counted.
    """

    per_group: dict[str, tuple[float, int]]
    mean: float
    std: float
    pooled: float
    num_pairs: int


class ErrorSummary(NamedTuple):
    """Accuracy at thresholds and the mean and median of per-pair errors.

    Attributes:
        accuracy: ``{threshold: percent of pairs with error < threshold}``.
        mean, median: of the finite errors (NaN when none); non-finite errors count as
            failures in ``accuracy``.
        num_pairs: pairs counted.
    """

    accuracy: dict[float, float]
    mean: float
    median: float
    num_pairs: int


def _check_points(points: torch.Tensor, name: str) -> None:
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"{name} must have shape (N, 3), got {tuple(points.shape)}")


def _as_tensor(x) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))


# ================================================================== feature matching


def nn_inlier_ratio(
    points_src: torch.Tensor,
    feats_src: torch.Tensor,
    points_tgt: torch.Tensor,
    feats_tgt: torch.Tensor,
    T_tgt_src: torch.Tensor,
    tau1: float = 0.10,
) -> MatchInliers:
    """Inlier ratio of feature nearest neighbours (FCGF's hit ratio).

    Objective: the smaller of the two sets (the source on a tie) is the query; each query
    point's nearest neighbour in feature space among the other set is its match; a match
    ``(p_src, q_tgt)`` is an inlier when ``|T p_src - q_tgt| < tau1``.

    Args:
        points_src: ``(N, 3)`` source points; ``feats_src``: ``(N, C)``.
        points_tgt: ``(M, 3)`` target points; ``feats_tgt``: ``(M, C)``.
        T_tgt_src: ``(4, 4)`` ground truth.
        tau1: inlier distance, in the units of the points.

    Returns:
        :class:`MatchInliers`; ratio 0 with 0 matches when a set is empty.

    Raises:
        ShapeError: mismatched shapes.
    """
    _check_points(points_src, "points_src")
    _check_points(points_tgt, "points_tgt")
    if feats_src.shape[0] != points_src.shape[0] or feats_tgt.shape[0] != points_tgt.shape[0]:
        raise ShapeError("each feature row must describe one point")
    n, m = points_src.shape[0], points_tgt.shape[0]
    if n == 0 or m == 0:
        return MatchInliers(0.0, 0, 0)
    moved = apply_transform(T_tgt_src.to(torch.float64), points_src.to(torch.float64))
    target = points_tgt.to(torch.float64)
    if n <= m:
        nn = feature_knn(feats_src, feats_tgt, k=1).idx[:, 0]
        dist = torch.linalg.vector_norm(moved - target[nn], dim=1)
    else:
        nn = feature_knn(feats_tgt, feats_src, k=1).idx[:, 0]
        dist = torch.linalg.vector_norm(target - moved[nn], dim=1)
    inliers = int((dist < tau1).sum())
    return MatchInliers(inliers / dist.numel(), int(dist.numel()), inliers)


def recall_by_group(
    recalled: Sequence[bool], groups: Sequence[str], values: Sequence[float] | None = None
) -> RecallSummary:
    """Recall per group, the mean and std over groups, and the pooled recall.

    Args:
        recalled: one flag per pair.
        groups: the pair's group (scene), same length.
        values: optional per-pair numbers to average instead of the flags (e.g. inlier
            ratios); then "recall" is that mean.

    Returns:
        :class:`RecallSummary`.

    Raises:
        ValueError: lengths differ.
    """
    flags = [float(v) for v in (values if values is not None else recalled)]
    if len(flags) != len(groups) or (values is not None and len(values) != len(recalled)):
        raise ValueError("one group per pair is needed")
    per: dict[str, list[float]] = {}
    for flag, group in zip(flags, groups, strict=True):
        per.setdefault(group, []).append(flag)
    per_group = {g: (float(np.mean(v)), len(v)) for g, v in per.items()}
    recalls = np.array([r for r, _ in per_group.values()], dtype=np.float64)
    nan = float("nan")
    return RecallSummary(
        per_group=per_group,
        mean=float(recalls.mean()) if recalls.size else nan,
        std=float(recalls.std()) if recalls.size else nan,
        pooled=float(np.mean(flags)) if flags else nan,
        num_pairs=len(flags),
    )


# ================================================================== registration


def quaternion_from_rotation(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix, with ``w >= 0``.

    Objective: the active-rotation quaternion, ``R = rotation of angle a about axis u`` gives
    ``(cos(a/2), sin(a/2) u)`` (Shepperd's method: the largest of ``w, x, y, z`` is computed
    from the diagonal, the others from the off-diagonal terms, for accuracy).

    Args:
        R: ``(3, 3)`` rotation (a ``(4, 4)`` transform is accepted).

    Returns:
        ``(4,)`` float64.
    """
    R = _as_tensor(R).to(torch.float64)[:3, :3]
    if R.shape != (3, 3):
        raise ShapeError(f"R must be (3, 3), got {tuple(R.shape)}")
    m = R
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = torch.stack([trace, m[0, 0], m[1, 1], m[2, 2]])
    k = int(torch.argmax(candidates))
    if k == 0:
        s = torch.sqrt(1.0 + trace) * 2.0
        q = torch.stack(
            [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        )
    elif k == 1:
        s = torch.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = torch.stack(
            [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        )
    elif k == 2:
        s = torch.sqrt(1.0 - m[0, 0] + m[1, 1] - m[2, 2]) * 2.0
        q = torch.stack(
            [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        )
    else:
        s = torch.sqrt(1.0 - m[0, 0] - m[1, 1] + m[2, 2]) * 2.0
        q = torch.stack(
            [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
        )
    q = q / torch.linalg.vector_norm(q)
    return -q if q[0] < 0 else q


def registration_rmse(T_est, T_gt, info) -> float:
    """Official 3DMatch registration error, as an RMSE in metres.

    Objective (3DMatch toolbox, Redwood benchmark, as also coded by FCGF and Predator): with
    the error transform ``E = inv(T_gt) @ T_est``, ``p = (t_E, q_E[1:])`` (its translation and
    the imaginary part of its unit quaternion, ``w >= 0``), the squared error is
    ``p^T info p / info[0, 0]``; ``info[0, 0]`` is the number of ground-truth
    correspondences (the top-left 3x3 block of ``gt.info`` is ``N * I``). The toolbox's recall
    counts a pair when this squared error is at most ``0.2^2``.

    Args:
        T_est, T_gt: ``(4, 4)`` ``T_tgt_src`` (tensors or arrays).
        info: ``(6, 6)`` information matrix of the pair.

    Returns:
        ``sqrt(max(0, p^T info p / info[0, 0]))``; NaN when ``info[0, 0] <= 0`` (a degenerate
        record; one 3DLoMatch pair has an all-zero matrix).
    """
    T_est = _as_tensor(T_est).to(torch.float64)
    T_gt = _as_tensor(T_gt).to(torch.float64)
    info = _as_tensor(info).to(torch.float64)
    if T_est.shape != (4, 4) or T_gt.shape != (4, 4) or info.shape != (6, 6):
        raise ShapeError("T_est and T_gt must be (4, 4) and info (6, 6)")
    if not float(info[0, 0]) > 0:
        return float("nan")
    E = torch.linalg.inv(T_gt) @ T_est
    p = torch.cat([E[:3, 3], quaternion_from_rotation(E[:3, :3])[1:]])
    err2 = float(p @ info @ p / info[0, 0])
    return math.sqrt(max(0.0, err2))


def pose_errors(T_est, T_gt) -> tuple[float, float]:
    """``(rotation error in degrees, translation error in the units of T)``.

    Rotation: ``arccos((tr(R_est R_gt^T) - 1) / 2)``; translation: ``|t_est - t_gt|``.
    """
    T_est = _as_tensor(T_est).to(torch.float64)
    T_gt = _as_tensor(T_gt).to(torch.float64)
    return float(rotation_error_deg(T_est, T_gt)), float(translation_error(T_est, T_gt))


def accuracy_at(values: Iterable[float], thresholds: Iterable[float]) -> dict[float, float]:
    """Percent of values strictly below each threshold (NaN/Inf values never are).

    Returns:
        ``{threshold: percent}``; NaN percentages when there is no value.
    """
    v = np.asarray(list(values), dtype=np.float64)
    out = {}
    for thr in thresholds:
        with np.errstate(invalid="ignore"):
            out[float(thr)] = 100.0 * float(np.mean(v < thr)) if v.size else float("nan")
    return out


def error_summary(values: Iterable[float], thresholds: Iterable[float]) -> ErrorSummary:
    """Accuracy at ``thresholds``, mean and median of per-pair errors (:class:`ErrorSummary`)."""
    v = np.asarray(list(values), dtype=np.float64)
    finite = v[np.isfinite(v)]
    nan = float("nan")
    return ErrorSummary(
        accuracy=accuracy_at(v, thresholds),
        mean=float(finite.mean()) if finite.size else nan,
        median=float(np.median(finite)) if finite.size else nan,
        num_pairs=int(v.size),
    )


# ================================================================== chamfer


def _nn_sq_dist(query: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Squared distance of each query point to its nearest reference point (open3d KD-tree)."""
    from byoc_cli.errors import require_open3d

    o3d = require_open3d()
    a = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(query)))
    b = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(ref)))
    return np.asarray(a.compute_point_cloud_distance(b), dtype=np.float64) ** 2


def chamfer_distance(points_a, points_b) -> float:
    """Symmetric chamfer distance with squared distances, in 1e-3 m^2 (points in metres).

    Objective: ``mean_a min_b |a - b|^2 + mean_b min_a |b - a|^2`` (PyTorch3D's
    ``chamfer_distance`` with its default mean reductions), times :data:`CHAMFER_SCALE`.

    Args:
        points_a: ``(N, 3)``; points_b: ``(M, 3)`` (tensors or arrays), N, M >= 1.

    Returns:
        The distance (0 for identical sets).

    Raises:
        ShapeError: wrong shapes or an empty set.
    """
    a = np.asarray(points_a, dtype=np.float64)
    b = np.asarray(points_b, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or b.ndim != 2 or b.shape[1] != 3:
        raise ShapeError("chamfer_distance needs two (N, 3) point sets")
    if not len(a) or not len(b):
        raise ShapeError("chamfer_distance needs non-empty point sets")
    return CHAMFER_SCALE * float(_nn_sq_dist(a, b).mean() + _nn_sq_dist(b, a).mean())


def fused_chamfer(points_src, points_tgt, T_est, T_gt) -> float:
    """Chamfer between the two frames fused with the estimated and with the true pose.

    Objective: ``chamfer(tgt ∪ T_est src, tgt ∪ T_gt src)`` (the paper's section 4.1); 0 when
    ``T_est == T_gt``. Units as :func:`chamfer_distance`.

    Args:
        points_src: ``(N, 3)`` source cloud; points_tgt: ``(M, 3)`` target cloud (metres).
        T_est, T_gt: ``(4, 4)`` ``T_tgt_src``.
    """
    src = np.asarray(points_src, dtype=np.float64)
    tgt = np.asarray(points_tgt, dtype=np.float64)
    T_est = np.asarray(T_est, dtype=np.float64)
    T_gt = np.asarray(T_gt, dtype=np.float64)
    fused_est = np.concatenate([tgt, src @ T_est[:3, :3].T + T_est[:3, 3]])
    fused_gt = np.concatenate([tgt, src @ T_gt[:3, :3].T + T_gt[:3, 3]])
    return chamfer_distance(fused_est, fused_gt)
