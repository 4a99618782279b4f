"""One Gauss-Newton step of plane-to-plane alignment (generalized ICP with planar covariances).

Generalized ICP (Segal, Haehnel and Thrun, RSS 2009) minimises
``sum_i w_i d_i^T (R C_p,i R^T + C_q,i)^-1 d_i`` with ``d_i = q_i - (R p_i + t)``: each point is a
small disc of its surface (covariance ``C = eps n n^T + (I - n n^T)``, thin along its normal
``n``). Where the discs of a pair face the same way the cost is point-to-plane; where they do
not (a floor point matched to a wall while the guess is still far) the sum of the two
covariances is nearly round and the pair pulls weakly. That is what widens its basin over
point-to-plane ICP's: from guesses 10 deg and 30 cm off on TUM pairs 50 frames apart, a coarse
pass of this step brought 27 of 50 starts within 5 deg and 10 cm where point-to-plane brought
20 (``benchmarks/init.py``; docs/poses.md).

Linearisation about the current points, with ``c`` their weighted mean and ``L`` their RMS
radius (rotation and translation columns in the same units): a motion ``xi = (w, v)`` moves
``p`` to ``p + (w / L) x (p - c) + v``.
"""

from __future__ import annotations

import numpy as np
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.fitting.point_to_plane import PlaneStep
from byoc_cli.geometry.transforms import axis_angle_matrix

#: the variance of a point's disc along its normal, as a share of the variance across it
FLATNESS = 1e-3


def disc_covariances(normals: torch.Tensor, flatness: float = FLATNESS) -> torch.Tensor:
    """``(K, 3, 3)`` covariances of unit discs with ``normals (K, 3)``:
    ``flatness n n^T + (I - n n^T)``."""
    outer = normals[:, :, None] * normals[:, None, :]
    eye = torch.eye(3, dtype=normals.dtype, device=normals.device)
    return eye - (1.0 - flatness) * outer


def plane_to_plane_step(
    p: torch.Tensor,
    n_p: torch.Tensor,
    q: torch.Tensor,
    n_q: torch.Tensor,
    weights: torch.Tensor | None = None,
    flatness: float = FLATNESS,
) -> PlaneStep:
    """The increment that moves the discs ``(p, n_p)`` onto the discs ``(q, n_q)``.

    Args (tensors or numpy arrays):
        p: ``(K, 3)`` source points (already under the current transform).
        n_p: ``(K, 3)`` their unit normals (rotated with them; the sign does not matter).
        q: ``(K, 3)`` their target points; ``n_q``: ``(K, 3)`` unit normals at ``q``.
        weights: ``(K,)`` non-negative weights; None = ones.
        flatness: a disc's variance along its normal over its variance across it.

    Returns:
        :class:`~byoc_cli.fitting.point_to_plane.PlaneStep` (``rank`` 6, or 0 and the identity
        when there is nothing to fit); ``eigenvalues`` of the normal equations, ascending,
        normalised to the largest.

    Raises:
        ShapeError: shapes differ or are not ``(K, 3)``.
    """
    shapes = (p.shape, n_p.shape, q.shape, n_q.shape)
    if p.ndim != 2 or p.shape[-1] != 3 or any(s != p.shape for s in shapes):
        raise ShapeError(f"p, n_p, q, n_q must all be (K, 3), got {', '.join(map(str, shapes))}")
    p, n_p, q, n_q = (torch.as_tensor(x).double() for x in (p, n_p, q, n_q))
    w = torch.ones(len(p), dtype=torch.float64) if weights is None else weights.double()
    if len(p) < 3 or float(w.sum()) <= 0:
        return PlaneStep(torch.eye(4, dtype=torch.float64), 0, torch.zeros(6, dtype=torch.float64))
    M = torch.linalg.inv(disc_covariances(n_p, flatness) + disc_covariances(n_q, flatness))
    M = M * w[:, None, None]
    c = (w[:, None] * p).sum(0) / w.sum()
    x = p - c
    radius = torch.sqrt((w * (x**2).sum(1)).sum() / w.sum()).clamp_min(1e-9)
    J = torch.zeros(len(p), 3, 6, dtype=torch.float64)
    J[:, :, :3] = _cross_matrices(x / radius)  # d residual / d (w / L)
    J[:, :, 3:] = -torch.eye(3, dtype=torch.float64)  # d residual / d v
    # M J row by row as three broadcast products, then one (6, 3K) x (3K, 6) product: a
    # batched matmul of K tiny matrices costs ten times as much on the CPU
    MJ = M[:, :, :1] * J[:, :1] + M[:, :, 1:2] * J[:, 1:2] + M[:, :, 2:] * J[:, 2:]
    rows, weighted = J.reshape(-1, 6), MJ.reshape(-1, 6)
    H = rows.T @ weighted
    g = weighted.T @ (q - p).reshape(-1)
    # the 6 x 6 solve in numpy: a dozen torch calls on tiny matrices cost more than it
    H, g, c, radius = H.numpy(), g.numpy(), c.numpy(), float(radius)
    lam = np.linalg.eigvalsh(H)
    ridge = 1e-12 * max(lam[-1], 1e-300)
    xi = -np.linalg.solve(H + ridge * np.eye(6), g)
    R = axis_angle_matrix(xi[:3] / radius)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c - R @ c + xi[3:]
    return PlaneStep(torch.from_numpy(T), 6, torch.from_numpy(lam / max(lam[-1], 1e-300)))


def _cross_matrices(x: torch.Tensor) -> torch.Tensor:
    """``(K, 3, 3)`` matrices ``[x]_x`` with ``[x]_x y = x cross y``, of ``x (K, 3)``."""
    zero = torch.zeros(len(x), dtype=x.dtype)
    return torch.stack(
        [
            torch.stack([zero, -x[:, 2], x[:, 1]], 1),
            torch.stack([x[:, 2], zero, -x[:, 0]], 1),
            torch.stack([-x[:, 1], x[:, 0], zero], 1),
        ],
        1,
    )
