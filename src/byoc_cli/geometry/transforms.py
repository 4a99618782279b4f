"""Rigid transforms as 4x4 matrices on column vectors, named ``T_tgt_src``.

``T_tgt_src`` brings a point expressed in the source frame into the target frame:
``x_tgt = R x_src + t``. Names cancel like matrix products:
``T_c_a = compose(T_c_b, T_b_a)``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from byoc_cli.errors import ShapeError


def _check_transform(T: torch.Tensor, name: str = "T") -> None:
    if T.shape[-2:] != (4, 4):
        raise ShapeError(f"{name} must have shape (..., 4, 4), got {tuple(T.shape)}")


def _check_points(points: torch.Tensor, name: str = "points") -> None:
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ShapeError(f"{name} must have shape (..., N, 3), got {tuple(points.shape)}")


def make_transform(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Build ``T`` from a rotation and a translation.

    Args:
        R: ``(..., 3, 3)`` rotation.
        t: ``(..., 3)`` translation.

    Returns:
        ``(..., 4, 4)`` transform with the same dtype and device as ``R``.
    """
    if R.shape[-2:] != (3, 3) or t.shape[-1] != 3:
        raise ShapeError(
            f"R must be (..., 3, 3) and t (..., 3), got {tuple(R.shape)}, {tuple(t.shape)}"
        )
    # torch.broadcast_shapes would import torch.fx's symbolic shapes (sympy): 0.3 s
    batch = np.broadcast_shapes(tuple(R.shape[:-2]), tuple(t.shape[:-1]))
    T = R.new_zeros(*batch, 4, 4)
    T[..., :3, :3] = R
    T[..., :3, 3] = t.to(R.dtype)
    T[..., 3, 3] = 1.0
    return T


def apply_transform(T_tgt_src: torch.Tensor, points_src: torch.Tensor) -> torch.Tensor:
    """Map source points into the target frame.

    Args:
        T_tgt_src: ``(..., 4, 4)`` transform.
        points_src: ``(..., N, 3)`` points in the source frame.

    Returns:
        ``(..., N, 3)`` points in the target frame, ``points_src @ R.T + t``.
    """
    _check_transform(T_tgt_src, "T_tgt_src")
    _check_points(points_src, "points_src")
    T = T_tgt_src.to(points_src.dtype)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    return points_src @ R.transpose(-1, -2) + t.unsqueeze(-2)


def invert_transform(T_tgt_src: torch.Tensor) -> torch.Tensor:
    """Invert a rigid transform exactly (``R^T``, ``-R^T t``).

    Args:
        T_tgt_src: ``(..., 4, 4)``.

    Returns:
        ``T_src_tgt`` of the same shape.
    """
    _check_transform(T_tgt_src, "T_tgt_src")
    R = T_tgt_src[..., :3, :3]
    t = T_tgt_src[..., :3, 3]
    Rt = R.transpose(-1, -2)
    return make_transform(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))


def compose(T_c_b: torch.Tensor, T_b_a: torch.Tensor) -> torch.Tensor:
    """Compose two transforms: ``T_c_a = T_c_b @ T_b_a``."""
    _check_transform(T_c_b, "T_c_b")
    _check_transform(T_b_a, "T_b_a")
    return T_c_b @ T_b_a.to(T_c_b.dtype)


def rotation_error_deg(R_est: torch.Tensor, R_gt: torch.Tensor) -> torch.Tensor:
    """Geodesic angle between rotations, ``arccos((tr(R_est R_gt^T) - 1) / 2)`` in degrees.

    Args:
        R_est, R_gt: ``(..., 3, 3)`` rotations (4x4 transforms are accepted too).

    Returns:
        ``(...)`` angles in degrees, in [0, 180].
    """
    R_est = R_est[..., :3, :3].to(torch.float64)
    R_gt = R_gt[..., :3, :3].to(torch.float64)
    trace = (R_est * R_gt).sum(dim=(-1, -2))  # tr(R_est R_gt^T)
    cos = ((trace - 1.0) / 2.0).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cos))


def translation_error(T_est: torch.Tensor, T_gt: torch.Tensor) -> torch.Tensor:
    """Euclidean distance between the translations of two ``(..., 4, 4)`` transforms."""
    return torch.linalg.vector_norm(
        T_est[..., :3, 3].to(torch.float64) - T_gt[..., :3, 3].to(torch.float64), dim=-1
    )


def correspondence_inlier_ratio(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    T_tgt_src: torch.Tensor,
    tau1: float = 0.10,
) -> float:
    """Share of correspondences ``(points_src[k], points_tgt[k])`` within ``tau1`` under T.

    Args:
        points_src, points_tgt: ``(K, 3)`` corresponding points.
        T_tgt_src: ``(4, 4)`` transform (usually the ground truth).
        tau1: inlier distance.

    Returns:
        The share in [0, 1]; 0 when ``K == 0``.

    Raises:
        ShapeError: points not ``(K, 3)`` or of different lengths.
    """
    for points, name in ((points_src, "points_src"), (points_tgt, "points_tgt")):
        if points.ndim != 2 or points.shape[1] != 3:
            raise ShapeError(f"{name} must have shape (N, 3), got {tuple(points.shape)}")
    if points_src.shape[0] != points_tgt.shape[0]:
        raise ShapeError("points_src and points_tgt must have the same number of rows")
    if points_src.shape[0] == 0:
        return 0.0
    moved = apply_transform(T_tgt_src.to(torch.float64), points_src.to(torch.float64))
    dist = torch.linalg.vector_norm(moved - points_tgt.to(torch.float64), dim=1)
    return float((dist < tau1).double().mean())


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula.

    Args:
        axis_angle: ``(..., 3)`` rotation vectors (axis times angle in radians).

    Returns:
        ``(..., 3, 3)`` rotation matrices.
    """
    theta = torch.linalg.vector_norm(axis_angle, dim=-1, keepdim=True)
    axis = axis_angle / theta.clamp_min(1e-12)
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*x.shape, 3, 3)
    s = torch.sin(theta)[..., None]
    c = torch.cos(theta)[..., None]
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device).expand_as(K)
    return eye + s * K + (1 - c) * (K @ K)


def axis_angle_matrix(axis_angle: np.ndarray) -> np.ndarray:
    """:func:`axis_angle_to_matrix` of one ``(3,)`` rotation vector in numpy: ``(3, 3)``
    float64 (the steps of the refinement, where a torch call costs more than the formula)."""
    theta = float(np.linalg.norm(axis_angle))
    x, y, z = np.asarray(axis_angle, dtype=np.float64) / max(theta, 1e-12)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(theta) * K + (1 - math.cos(theta)) * (K @ K)


def axis_angle_matrices(axis_angle: np.ndarray) -> np.ndarray:
    """:func:`axis_angle_to_matrix` of ``(S, 3)`` rotation vectors in numpy: ``(S, 3, 3)``
    float64 (the batched steps of the restarts)."""
    v = np.asarray(axis_angle, dtype=np.float64)
    theta = np.linalg.norm(v, axis=1)[:, None, None]  # (S, 1, 1)
    x, y, z = (v / np.maximum(theta[:, :, 0], 1e-12)).T
    zero = np.zeros_like(x)
    K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=1).reshape(-1, 3, 3)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)


def random_rigid_transform(
    max_angle_deg: float,
    max_translation: float,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """Draw a random rigid transform.

    The axis is uniform on the sphere, the angle uniform in ``[0, max_angle_deg)``; the
    translation has a uniform direction and a length uniform in ``[0, max_translation)``.

    Returns:
        ``(4, 4)`` transform.
    """
    kw = {"generator": generator, "dtype": dtype, "device": device}
    axis = torch.randn(3, **kw)
    axis = axis / torch.linalg.vector_norm(axis).clamp_min(1e-12)
    angle = torch.rand((), **kw) * math.radians(max_angle_deg)
    direction = torch.randn(3, **kw)
    direction = direction / torch.linalg.vector_norm(direction).clamp_min(1e-12)
    length = torch.rand((), **kw) * max_translation
    return make_transform(axis_angle_to_matrix(axis * angle), direction * length)
