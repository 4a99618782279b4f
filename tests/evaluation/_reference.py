"""An independent brute-force reference for the 3DMatch evaluation figures.

Only numpy, plain Python parsing and explicit loops: full float64 distance matrices, ties
handled explicitly. Where the library's choice is not determined (two feature neighbours at
the same distance, equal ratio weights at the top-k boundary) the reference returns the
bounds of every valid choice, so that a check never depends on tie-breaking.

Shared with the library on purpose (they define the inputs, not the computations under test):
the protocol constants and the sampling rule, re-implemented here from their documentation.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import torch

#: Distances (or weights) closer than this are treated as ties (float32 features).
TIE_EPS = 1e-5


def parse_blocks(path: Path, rows: int) -> dict[tuple[int, int], np.ndarray]:
    """``{(i, j): matrix}`` from a gt.log (rows=4) or gt.info (rows=6), plainly."""
    lines = [line.split() for line in Path(path).read_text().splitlines() if line.strip()]
    out = {}
    for k in range(0, len(lines), rows + 1):
        i, j = int(lines[k][0]), int(lines[k][1])
        out[(i, j)] = np.array([[float(v) for v in row] for row in lines[k + 1 : k + 1 + rows]])
    return out


def pair_seed(seed: int, scene: str, i: int, j: int) -> int:
    """As documented: sha256 of ``"seed/scene/i/j"``, first 8 bytes little-endian, >> 1."""
    digest = hashlib.sha256(f"{seed}/{scene}/{i}/{j}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def sample(num_src: int, num_tgt: int, count: int, seed: int):
    """Sorted random subsets: one torch generator, source drawn first (all when n <= count)."""
    generator = torch.Generator().manual_seed(seed)
    out = []
    for n in (num_src, num_tgt):
        if n <= count:
            out.append(np.arange(n))
        else:
            out.append(np.sort(torch.randperm(n, generator=generator)[:count].numpy()))
    return out


def _neighbours(fq: np.ndarray, fr: np.ndarray, pq: np.ndarray, pr: np.ndarray, tau1: float):
    """Per query row: d1, d2 (two smallest cosine distances), whether ANY / ALL of the
    feature neighbours tied at d1 are geometric inliers (|pq - pr| < tau1)."""
    fq = fq.astype(np.float64)
    fr = fr.astype(np.float64)
    n = fq.shape[0]
    d1 = np.empty(n)
    d2 = np.empty(n)
    any_in = np.zeros(n, bool)
    all_in = np.zeros(n, bool)
    sq_r = (fr**2).sum(1)
    for start in range(0, n, 1000):
        rows = slice(start, min(n, start + 1000))
        D = 0.5 * ((fq[rows] ** 2).sum(1)[:, None] + sq_r[None, :] - 2.0 * fq[rows] @ fr.T)
        two = np.sort(np.partition(D, 1, axis=1)[:, :2], axis=1)
        d1[rows], d2[rows] = two[:, 0], two[:, 1]
        local, col = np.nonzero(D <= two[:, :1] + TIE_EPS)  # every neighbour tied at d1
        inlier = np.linalg.norm(pr[col] - pq[rows.start + local], axis=1) < tau1
        num_tied = np.bincount(local, minlength=D.shape[0])
        num_in = np.bincount(local, weights=inlier, minlength=D.shape[0])
        any_in[rows], all_in[rows] = num_in > 0, num_in == num_tied
    return d1, d2, any_in, all_in


def nn_inlier_bounds(ps, fs, pt, ft, T, tau1):
    """Bounds ``(lo, hi, num_matches)`` of FCGF's NN inlier count (smaller set queries)."""
    moved = ps @ T[:3, :3].T + T[:3, 3]
    if len(ps) <= len(pt):
        _, _, any_in, all_in = _neighbours(fs, ft, moved, pt, tau1)
    else:
        _, _, any_in, all_in = _neighbours(ft, fs, pt, moved, tau1)
    return int(all_in.sum()), int(any_in.sum()), len(any_in)


def _topk_bounds(weight, any_in, all_in, k):
    """Inlier-count bounds over every valid top-k selection by weight (ties at the edge)."""
    n = len(weight)
    if k >= n:
        return int(all_in.sum()), int(any_in.sum())
    w_k = np.sort(weight)[::-1][k - 1]
    certain = weight > w_k + TIE_EPS
    edge = np.abs(weight - w_k) <= TIE_EPS
    need = k - int(certain.sum())
    lo = int(all_in[certain].sum()) + max(0, need - int((edge & ~all_in).sum()))
    hi = int(any_in[certain].sum()) + min(need, int((edge & any_in).sum()))
    return lo, hi


def corr_inlier_bounds(ps, fs, pt, ft, T, tau1, k):
    """Bounds ``(lo, hi, num_correspondences)`` of the inlier count of the top-k ratio-test
    correspondences in both directions (w = 1 - d1 / d2, distances clamped at 1e-9)."""
    moved = ps @ T[:3, :3].T + T[:3, 3]
    lo = hi = total = 0
    for fq, fr, pq, pr in ((fs, ft, moved, pt), (ft, fs, pt, moved)):
        d1, d2, any_in, all_in = _neighbours(fq, fr, pq, pr, tau1)
        weight = 1.0 - np.maximum(d1, 1e-9) / np.maximum(d2, 1e-9)
        a, b = _topk_bounds(weight, any_in, all_in, k)
        lo, hi, total = lo + a, hi + b, total + min(k, len(weight))
    return lo, hi, total


def quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, as the top eigenvector of Bar-Itzhack's K."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = R
    K = (
        np.array(
            [
                [m00 - m11 - m22, m10 + m01, m20 + m02, m21 - m12],
                [m10 + m01, m11 - m00 - m22, m21 + m12, m02 - m20],
                [m20 + m02, m21 + m12, m22 - m00 - m11, m10 - m01],
                [m21 - m12, m02 - m20, m10 - m01, m00 + m11 + m22],
            ]
        )
        / 3.0
    )
    values, vectors = np.linalg.eigh(K)
    x, y, z, w = vectors[:, np.argmax(values)]
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


def rmse(T_est: np.ndarray, T_gt: np.ndarray, info: np.ndarray) -> float:
    """The toolbox RMSE: sqrt(p^T info p / info[0,0]), p = (t, q_xyz) of inv(T_gt) T_est."""
    if info[0, 0] <= 0:
        return math.nan
    E = np.linalg.solve(T_gt, T_est)
    p = np.concatenate([E[:3, 3], quaternion(E[:3, :3])[1:]])
    return math.sqrt(max(0.0, float(p @ info @ p) / info[0, 0]))


def rotation_error_deg(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    c = (np.trace(T_est[:3, :3] @ T_gt[:3, :3].T) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))
