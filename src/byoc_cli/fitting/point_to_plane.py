"""One Gauss-Newton step of point-to-plane alignment that holds degenerate directions.

Point-to-plane ICP minimises ``sum_i w_i (n_i . (T p_i - q_i))^2``. On scenes of a few
large planes (a cabinet on a floor, a corridor) the objective is nearly flat along some
motions (sliding along the planes), and plain ICP drifts along them by whatever the noise
says: started at the ground truth of the 28 ``tum_fr3_cabinet`` pairs (spacing 2), the plain
multiscale ICP ended more than 10 cm away on 9 of them, this step on 2
(``benchmarks/estimators.py --from-gt``, docs). So the translations along directions that
almost no normal faces (``sum w (n . e)^2`` below ``sliding`` times the largest) are not
moved: there the previous estimate (from feature matching) is kept. Following Zhang, Kaess
and Singh ("On degeneracy of optimization-based state estimation problems", ICRA 2016), the
remaining step is solved in the eigenbasis of the normal equations, and directions whose
eigenvalue is below ``degeneracy`` times the largest can be held too (off by default: at
0.05 it lost pairs on ``tum_fr1_desk_full``).

Linearisation about the current points, with ``c`` their mean and ``L`` their RMS radius
(so rotation and translation columns have the same units): a motion ``xi = (w, v)`` moves
``p`` to ``p + (w / L) x (p - c) + v``; the residual row is ``[((p - c) x n) / L, n]``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.transforms import axis_angle_matrices, axis_angle_matrix

#: directions with eigenvalue below this share of the largest are held (0 = none)
DEGENERACY = 0.0
#: translations along directions that normals face less than this share are held
SLIDING = 0.02


class PlaneStep(NamedTuple):
    """Outcome of :func:`point_to_plane_step`.

    Attributes:
        T: ``(4, 4)`` float64 increment; apply as ``T @ T_current``.
        rank: directions moved (0 to 6).
        eigenvalues: ``(6,)`` of the normal equations, ascending, normalised to the largest.
    """

    T: torch.Tensor
    rank: int
    eigenvalues: torch.Tensor


def point_to_plane_step(
    p: torch.Tensor,
    q: torch.Tensor,
    n: torch.Tensor,
    weights: torch.Tensor | None = None,
    degeneracy: float = DEGENERACY,
    sliding: float = SLIDING,
) -> PlaneStep:
    """The increment that moves points ``p`` onto the planes ``(q, n)``.

    Args (tensors or numpy arrays):
        p: ``(K, 3)`` source points (already under the current transform).
        q: ``(K, 3)`` their target points.
        n: ``(K, 3)`` unit normals at ``q``.
        weights: ``(K,)`` non-negative weights; None = ones.
        degeneracy: eigenvalue share below which a direction is held; 0 = plain
            point-to-plane (every direction with a non-zero eigenvalue moves).
        sliding: translations along directions ``e`` with ``sum w (n . e)^2`` below this
            share of the largest (few surfaces face them: sliding along planes) are held.

    Returns:
        :class:`PlaneStep`; the identity with rank 0 when there is nothing to fit.

    Raises:
        ShapeError: shapes differ or are not ``(K, 3)``.
    """
    if p.ndim != 2 or p.shape[-1] != 3 or q.shape != p.shape or n.shape != p.shape:
        raise ShapeError(f"p, q, n must all be (K, 3), got {p.shape}, {q.shape}, {n.shape}")
    p, q, n = (_array(x) for x in (p, q, n))
    w = None if weights is None else _array(weights)
    total = float(len(p)) if w is None else float(w.sum())
    if len(p) == 0 or total <= 0:
        return PlaneStep(torch.eye(4, dtype=torch.float64), 0, torch.zeros(6, dtype=torch.float64))
    c = (p if w is None else w[:, None] * p).sum(0) / total
    centred = p - c
    spread = (centred**2).sum(1)
    radius = max(math.sqrt((spread if w is None else w * spread).sum() / total), 1e-9)
    J = np.concatenate([np.cross(centred, n) / radius, n], axis=1)  # (K, 6)
    r = ((p - q) * n).sum(1)
    H = J.T @ (J if w is None else w[:, None] * J)
    g = -(J.T @ (r if w is None else w * r))
    B = _free_basis(n, w, sliding)  # (6, d): the motions allowed to move
    lam, U = np.linalg.eigh(B.T @ H @ B)
    top = max(lam[-1], 1e-300)
    keep = lam > max(degeneracy, 1e-12) * top
    xi = B @ (U[:, keep] @ ((U[:, keep].T @ (B.T @ g)) / lam[keep]))
    R = axis_angle_matrix(xi[:3] / radius)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c - R @ c + xi[3:]
    full = np.linalg.eigvalsh(H)
    return PlaneStep(
        torch.from_numpy(T), int(keep.sum()), torch.from_numpy(full / max(full[-1], 1e-300))
    )


def _array(x: torch.Tensor | np.ndarray) -> np.ndarray:
    """``x`` (a tensor or an array) as a float64 numpy array: the step runs in numpy (dozens
    of torch calls on 6 x 6 matrices cost more than their arithmetic, and every one of them
    hands the interpreter lock to the other worker thread and waits to get it back)."""
    if isinstance(x, torch.Tensor):
        x = x.detach().to(device="cpu", dtype=torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def _free_basis(n: np.ndarray, w: np.ndarray | None, sliding: float) -> np.ndarray:
    """``(6, d)`` orthonormal basis of the motions whose translation part avoids the
    directions that almost no normal in ``n (K, 3)`` faces (weights ``w (K,)``)."""
    mu, E = np.linalg.eigh((n.T if w is None else n.T * w) @ n)
    held = E[:, mu < sliding * max(mu[-1], 1e-300)]  # (3, h)
    basis = np.eye(6)
    if held.shape[1] == 0:
        return basis
    C = np.zeros((6, held.shape[1]))
    C[3:] = held
    U, _, _ = np.linalg.svd(basis - C @ C.T)
    return U[:, : 6 - held.shape[1]]


def point_to_plane_steps(
    p: torch.Tensor | np.ndarray,
    q: torch.Tensor | np.ndarray,
    n: torch.Tensor | np.ndarray,
    weights: torch.Tensor | np.ndarray,
    degeneracy: float = DEGENERACY,
    sliding: float = SLIDING,
) -> torch.Tensor:
    """:func:`point_to_plane_step` of ``S`` problems at once (the restarts of a refinement:
    one call instead of ``S``), in numpy as the single step is.

    The held translations are projected out instead of cut from the basis (``P H P`` has
    eigenvalue 0 along them, which the ``degeneracy`` floor drops), so a step agrees with
    :func:`point_to_plane_step` up to rounding, not to the last bit.

    Args (tensors or numpy arrays):
        p, q, n: ``(S, K, 3)`` source points, their target points and unit normals.
        weights: ``(S, K)`` non-negative weights (0: a point that does not take part).
        degeneracy, sliding: as :func:`point_to_plane_step`.

    Returns:
        ``(S, 4, 4)`` float64 increments (the identity where a problem's weights are all 0).

    Raises:
        ShapeError: shapes differ or are not ``(S, K, 3)`` and ``(S, K)``.
    """
    if p.ndim != 3 or p.shape[-1] != 3 or q.shape != p.shape or n.shape != p.shape:
        raise ShapeError(f"p, q, n must all be (S, K, 3), got {p.shape}, {q.shape}, {n.shape}")
    if tuple(weights.shape) != tuple(p.shape[:2]):
        raise ShapeError(f"weights must be (S, K) = {tuple(p.shape[:2])}, got {weights.shape}")
    p, q, n, w = (_array(x) for x in (p, q, n, weights))
    total = w.sum(1)  # (S,)
    safe = np.maximum(total, 1e-300)
    c = np.einsum("sk,skd->sd", w, p) / safe[:, None]  # (S, 3)
    centred = p - c[:, None]
    radius = np.maximum(np.sqrt((w * (centred**2).sum(2)).sum(1) / safe), 1e-9)  # (S,)
    J = np.concatenate([np.cross(centred, n) / radius[:, None, None], n], axis=2)  # (S, K, 6)
    r = ((p - q) * n).sum(2)  # (S, K)
    H = J.transpose(0, 2, 1) @ (w[..., None] * J)  # (S, 6, 6)
    g = -np.einsum("skd,sk->sd", J, w * r)  # (S, 6)
    P = _free_projector(n, w, sliding)
    lam, U = np.linalg.eigh(P @ H @ P)
    top = np.maximum(lam[:, -1:], 1e-300)
    keep = (lam > max(degeneracy, 1e-12) * top) & (total > 0)[:, None]
    inverse = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    Pg = (P @ g[..., None])[..., 0]
    xi = (U @ (inverse * (U.transpose(0, 2, 1) @ Pg[..., None])[..., 0])[..., None])[..., 0]
    R = axis_angle_matrices(xi[:, :3] / radius[:, None])
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = c - (R @ c[..., None])[..., 0] + xi[:, 3:]
    return torch.from_numpy(T)


def _free_projector(n: np.ndarray, w: np.ndarray, sliding: float) -> np.ndarray:
    """``(S, 6, 6)`` projector onto the motions of :func:`_free_basis`, for normals
    ``n (S, K, 3)`` and weights ``w (S, K)``."""
    mu, E = np.linalg.eigh((n.transpose(0, 2, 1) * w[:, None]) @ n)  # (S, 3), (S, 3, 3)
    held = (mu < sliding * np.maximum(mu[:, -1:], 1e-300)).astype(np.float64)  # (S, 3)
    C = np.zeros((len(n), 6, 3))
    C[:, 3:] = E * held[:, None, :]
    return np.eye(6) - C @ C.transpose(0, 2, 1)
