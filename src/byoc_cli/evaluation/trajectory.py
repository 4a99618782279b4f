"""Trajectory errors as the TUM RGB-D benchmark defines them (Sturm et al., IROS 2012).

Trajectories are camera-to-world poses ``T_world_cam (N, 4, 4)`` float64, the estimate and
the ground truth given for the same ``N`` frames (associated beforehand, e.g. by timestamp).

* ATE (``evaluate_ate.py``): the estimated camera centres are aligned to the ground-truth
  centres by the least-squares rigid motion (Horn / Umeyama, no scale); the error of a frame
  is the distance between its aligned and its true centre; reported as RMSE (and mean,
  median, max).
* RPE (``evaluate_rpe.py`` with ``--fixed_delta``): for each frame ``i``, the frame ``j``
  whose index (seconds or frame number) is closest to ``index[i] + delta``; with the motions
  ``M_est = inv(P_i) P_j`` and ``M_gt = inv(Q_i) Q_j`` (``P`` estimate, ``Q`` truth) the error
  of the pair is the script's ``ominus(ominus(P_j, P_i), ominus(Q_j, Q_i)) =
  M_est @ inv(M_gt)``, its translation norm and rotation angle; reported as RMSE of each.
  As in the TUM script, a pair whose ``j`` is the last frame is left out (the script cannot
  tell a true match at the end from one clamped there).

Pure numpy; no I/O.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from byoc_cli.errors import ShapeError

__all__ = [
    "AteResult",
    "RpeResult",
    "absolute_trajectory_error",
    "align_rigid",
    "relative_pose_error",
]


class AteResult(NamedTuple):
    """Absolute trajectory error.

    Attributes:
        rmse, mean, median, max: of the per-frame errors (metres).
        errors: ``(N,)`` per-frame distances after the alignment.
        T_gt_est: ``(4, 4)`` the rigid alignment applied to the estimate.
    """

    rmse: float
    mean: float
    median: float
    max: float
    errors: np.ndarray
    T_gt_est: np.ndarray


class RpeResult(NamedTuple):
    """Relative pose error over a fixed delta.

    Attributes:
        translation_rmse: RMSE of the translation errors (metres per delta).
        rotation_rmse_deg: RMSE of the rotation errors (degrees per delta).
        translation_mean, rotation_mean_deg: means of the same.
        num_pairs: pairs compared (0: the trajectory is shorter than delta; figures NaN).
        delta, unit: the delta and its unit (``"s"`` or ``"frames"``).
    """

    translation_rmse: float
    rotation_rmse_deg: float
    translation_mean: float
    rotation_mean_deg: float
    num_pairs: int
    delta: float
    unit: str


def _check(poses_est: np.ndarray, poses_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est = np.asarray(poses_est, dtype=np.float64)
    gt = np.asarray(poses_gt, dtype=np.float64)
    if est.ndim != 3 or est.shape[1:] != (4, 4) or est.shape != gt.shape:
        raise ShapeError(
            f"poses_est and poses_gt must both be (N, 4, 4), got {est.shape} and {gt.shape}"
        )
    if not (np.all(np.isfinite(est)) and np.all(np.isfinite(gt))):
        raise ShapeError("a pose has NaN or Inf entries")
    return est, gt


def align_rigid(points_src: np.ndarray, points_tgt: np.ndarray) -> np.ndarray:
    """Least-squares rigid motion (no scale) taking ``points_src`` onto ``points_tgt``.

    Minimises ``sum_i |R src_i + t - tgt_i|^2`` (Horn 1987; Umeyama 1991 with the reflection
    guard, scale fixed to 1).

    Args:
        points_src, points_tgt: ``(N, 3)`` corresponding points, ``N >= 1``.

    Returns:
        ``T_tgt_src (4, 4)`` float64 (for ``N < 3`` or collinear points, one of the minimisers).

    Raises:
        ShapeError: shapes differ, are not ``(N, 3)`` or N is 0.
    """
    src = np.asarray(points_src, dtype=np.float64)
    tgt = np.asarray(points_tgt, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != tgt.shape or len(src) == 0:
        raise ShapeError(f"need two (N, 3) arrays with N >= 1, got {src.shape} and {tgt.shape}")
    mu_src, mu_tgt = src.mean(axis=0), tgt.mean(axis=0)
    cov = (tgt - mu_tgt).T @ (src - mu_src)
    U, _, Vt = np.linalg.svd(cov)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ D @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_tgt - R @ mu_src
    return T


def absolute_trajectory_error(poses_est: np.ndarray, poses_gt: np.ndarray) -> AteResult:
    """ATE of ``poses_est`` against ``poses_gt`` (both ``(N, 4, 4)``, ``N >= 1``).

    Raises:
        ShapeError: the shapes differ, are not ``(N, 4, 4)``, N is 0, or a pose is not finite.
    """
    est, gt = _check(poses_est, poses_gt)
    T = align_rigid(est[:, :3, 3], gt[:, :3, 3])
    aligned = est[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    errors = np.linalg.norm(aligned - gt[:, :3, 3], axis=1)
    return AteResult(
        rmse=float(np.sqrt(np.mean(errors**2))),
        mean=float(errors.mean()),
        median=float(np.median(errors)),
        max=float(errors.max()),
        errors=errors,
        T_gt_est=T,
    )


def _closest(index: np.ndarray, value: float) -> int:
    """Position of the entry of the sorted ``index`` closest to ``value`` (first on a tie)."""
    k = int(np.searchsorted(index, value))
    if k == 0:
        return 0
    if k == len(index):
        return len(index) - 1
    return k - 1 if value - index[k - 1] <= index[k] - value else k


def _angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def relative_pose_error(
    poses_est: np.ndarray,
    poses_gt: np.ndarray,
    stamps: np.ndarray | None = None,
    delta: float = 1.0,
) -> RpeResult:
    """RPE over a fixed ``delta`` (seconds with ``stamps``, else frames).

    Args:
        poses_est, poses_gt: ``(N, 4, 4)`` for the same frames.
        stamps: ``(N,)`` increasing timestamps in seconds, or None (delta in frames).
        delta: the interval (> 0).

    Returns:
        :class:`RpeResult` (NaN figures and ``num_pairs == 0`` when no pair is ``delta``
        apart before the last frame).

    Raises:
        ShapeError: shapes differ, ``stamps`` is not ``(N,)`` increasing, ``delta <= 0``.
    """
    est, gt = _check(poses_est, poses_gt)
    if not delta > 0:
        raise ShapeError(f"delta must be > 0, got {delta}")
    n = len(est)
    if stamps is None:
        index, unit = np.arange(n, dtype=np.float64), "frames"
    else:
        index, unit = np.asarray(stamps, dtype=np.float64).reshape(-1), "s"
        if len(index) != n or np.any(np.diff(index) <= 0) or not np.all(np.isfinite(index)):
            raise ShapeError(f"stamps must be ({n},) finite and increasing")
    trans, rot = [], []
    for i in range(n):
        j = _closest(index, index[i] + delta)
        if j == n - 1:  # evaluate_rpe.py: the last frame is never the end of a pair
            continue
        motion_est = np.linalg.inv(est[i]) @ est[j]
        motion_gt = np.linalg.inv(gt[i]) @ gt[j]
        error = motion_est @ np.linalg.inv(motion_gt)
        trans.append(float(np.linalg.norm(error[:3, 3])))
        rot.append(_angle_deg(error[:3, :3]))
    if not trans:
        return RpeResult(math.nan, math.nan, math.nan, math.nan, 0, float(delta), unit)
    trans_a, rot_a = np.asarray(trans), np.asarray(rot)
    return RpeResult(
        translation_rmse=float(np.sqrt(np.mean(trans_a**2))),
        rotation_rmse_deg=float(np.sqrt(np.mean(rot_a**2))),
        translation_mean=float(trans_a.mean()),
        rotation_mean_deg=float(rot_a.mean()),
        num_pairs=len(trans),
        delta=float(delta),
        unit=unit,
    )
