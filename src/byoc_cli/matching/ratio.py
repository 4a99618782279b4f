"""Feature nearest neighbours (chunked brute force) and Lowe-ratio correspondences.

Features are unit vectors (L2-normalised); their distance is the cosine distance
``D = 1 - cos(a, b) = |a - b|^2 / 2``. This module computes ``|a - b|^2 / 2``, which equals
``1 - cos`` on unit vectors and stays a proper (squared) distance when they are not.

Neighbour *selection* runs without autograd on the expanded form
``|b|^2 - 2 a.b`` (one matmul per chunk of query rows, so memory stays bounded); the
distances that are returned are then recomputed exactly as ``|a - b|^2 / 2`` for the
selected pairs only. That makes them accurate near zero and differentiable with respect to
both feature sets, without autograd ever holding an ``N x M`` matrix.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from itertools import pairwise
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.errors import ShapeError

#: Bytes of distance matrix computed at once by :func:`feature_knn` when ``chunk_size`` is None
#: (small enough to stay in cache: on CPU 8 MB chunks select neighbours about twice as fast as
#: 64 MB ones).
CHUNK_BYTES = 8 * 2**20

#: Distances are clamped at this value before the Lowe ratio ``D(nn1) / D(nn2)``.
RATIO_EPS = 1e-9


class KNN(NamedTuple):
    """Nearest neighbours of the query rows among the reference rows.

    Attributes:
        dist: ``(N, k)`` cosine distances ``|a - b|^2 / 2``, ascending along each row;
            differentiable with respect to both feature sets.
        idx: ``(N, k)`` int64; ``idx[i, j] = m`` means ``feats_ref[m]`` is the ``j``-th
            nearest neighbour of ``feats_query[i]``.
    """

    dist: torch.Tensor
    idx: torch.Tensor


class Correspondences(NamedTuple):
    """Putative matches ``points_src[src_idx[i]] <-> points_tgt[tgt_idx[i]]``.

    Attributes:
        src_idx: ``(K,)`` int64 indices into the source cloud.
        tgt_idx: ``(K,)`` int64 indices into the target cloud.
        weight: ``(K,)`` float Lowe-ratio weights in ``[0, 1]`` (differentiable with respect
            to the features).
    """

    src_idx: torch.Tensor
    tgt_idx: torch.Tensor
    weight: torch.Tensor


def _check_feats(feats: torch.Tensor, name: str) -> None:
    if feats.ndim != 2:
        raise ShapeError(f"{name} must have shape (N, C), got {tuple(feats.shape)}")
    if not feats.is_floating_point():
        raise ShapeError(f"{name} must be a floating-point tensor, got {feats.dtype}")


def _check_pair(feats_a: torch.Tensor, feats_b: torch.Tensor, name_a: str, name_b: str) -> None:
    _check_feats(feats_a, name_a)
    _check_feats(feats_b, name_b)
    if feats_a.shape[1] != feats_b.shape[1]:
        raise ShapeError(
            f"{name_a} and {name_b} must have the same number of channels, "
            f"got {feats_a.shape[1]} and {feats_b.shape[1]}"
        )
    if feats_a.device != feats_b.device:
        raise ShapeError(f"{name_a} and {name_b} are on different devices")


def _auto_chunk(num_ref: int, dtype: torch.dtype) -> int:
    itemsize = torch.empty((), dtype=dtype).element_size()
    return max(1, CHUNK_BYTES // max(1, num_ref * itemsize))


def _pair_dist(query: torch.Tensor, ref: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``|query[i] - ref[idx[i, j]]|^2 / 2`` for ``(N, k)`` indices (differentiable)."""
    diff = query.unsqueeze(1) - ref[idx]
    return diff.square().sum(-1) * 0.5


def feature_knn(
    feats_query: torch.Tensor,
    feats_ref: torch.Tensor,
    k: int = 2,
    chunk_size: int | None = None,
) -> KNN:
    """Brute-force ``k`` nearest neighbours in feature space (cosine distance).

    Objective: for each query row ``a`` the ``k`` reference rows ``b`` with the smallest
    ``|a - b|^2 / 2`` (``= 1 - cos`` for unit features). The search is exact; it runs over
    chunks of query rows so that about 8 MB of distance matrix exists at once
    (``100k x 100k`` works in bounded memory). Deterministic for given inputs and device.

    Args:
        feats_query: ``(N, C)`` query features.
        feats_ref: ``(M, C)`` reference features (same device, same ``C``).
        k: neighbours per query row (>= 0); clipped to ``M``.
        chunk_size: query rows per chunk; ``None`` picks it from :data:`CHUNK_BYTES`.

    Returns:
        :class:`KNN` with ``(N, min(k, M))`` distances (the common floating dtype of the
        inputs, ascending) and int64 indices, on the inputs' device.

    Raises:
        ShapeError: inputs are not 2-D floating tensors with the same channel count.
        ValueError: ``k < 0`` or ``chunk_size < 1``.
    """
    _check_pair(feats_query, feats_ref, "feats_query", "feats_ref")
    if k < 0:
        raise ValueError(f"k must be >= 0, got {k}")
    if chunk_size is not None and chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    dtype = torch.promote_types(feats_query.dtype, feats_ref.dtype)
    query = feats_query.to(dtype)
    ref = feats_ref.to(dtype)
    n, m = query.shape[0], ref.shape[0]
    k = min(k, m)
    if n == 0 or k == 0:
        idx = torch.zeros(n, k, dtype=torch.int64, device=query.device)
        return KNN(_pair_dist(query, ref, idx), idx)

    chunk = chunk_size or _auto_chunk(m, dtype)
    with torch.no_grad():
        q = query.detach()
        r = ref.detach()
        ref_sq = r.square().sum(-1)  # |b|^2; |a|^2 is constant along a row
        parts = []
        for start in range(0, n, chunk):
            score = torch.addmm(ref_sq, q[start : start + chunk], r.T, alpha=-2.0)
            parts.append(_smallest_columns(score, k))
        idx = torch.cat(parts) if len(parts) > 1 else parts[0]

    dist = _pair_dist(query, ref, idx)
    if k > 1:  # exact distances can reorder near-ties of the expanded form
        order = torch.sort(dist.detach(), dim=1, stable=True).indices
        dist = dist.gather(1, order)
        idx = idx.gather(1, order)
    return KNN(dist, idx)


def _smallest_columns(score: torch.Tensor, k: int) -> torch.Tensor:
    """The columns of the ``k`` smallest values of each row of ``score (R, M)``, ascending, as
    ``(R, k)`` int64: ``torch.topk``'s.

    For ``k <= 2`` on the CPU: numpy's ``argmin`` two or three times, each value found masked
    for the next (5000 x 5000 in 8 MB chunks: 0.015 s against 0.048 s for ``topk``). The rows
    whose three smallest are not all distinct (FPFH's equal histograms), or that hold a NaN,
    go to ``topk`` (row by row it orders each alike, whatever the other rows): the two orders
    of equal values differ, and with them the correspondence of a tie.
    """
    if k > 2 or score.device.type != "cpu" or score.dtype not in (torch.float32, torch.float64):
        return torch.topk(score, k, dim=1, largest=False, sorted=True).indices
    values = score.numpy()
    rows = np.arange(values.shape[0])
    found, least = [], []
    for _ in range(min(k + 1, values.shape[1])):  # one more: a tie with the last one taken
        column = values.argmin(axis=1)
        found.append(column)
        least.append(values[rows, column])
        values[rows, column] = np.inf
    for column, value in reversed(list(zip(found, least, strict=True))):  # score as it came
        values[rows, column] = value
    distinct = np.ones(len(rows), dtype=bool)
    for a, b in pairwise(least):
        distinct &= a < b  # False at a tie, and where argmin stopped at a NaN
    columns = torch.from_numpy(np.stack(found[:k], axis=1))
    if not distinct.all():
        tied = torch.from_numpy(np.flatnonzero(~distinct))
        columns[tied] = torch.topk(score[tied], k, dim=1, largest=False, sorted=True).indices
    return columns


def _one_by_one(calls: Sequence[Callable[[], KNN]]) -> list[KNN]:
    return [call() for call in calls]


def _empty(feats_src: torch.Tensor, feats_tgt: torch.Tensor) -> Correspondences:
    idx = torch.zeros(0, dtype=torch.int64, device=feats_src.device)
    # slices of the inputs: typed, on the right device, and attached to the graph
    weight = feats_src.reshape(-1)[:0] + feats_tgt.reshape(-1)[:0]
    return Correspondences(idx, idx.clone(), weight)


def _ratio_weight(knn: KNN) -> torch.Tensor:
    d1 = knn.dist[:, 0].clamp_min(RATIO_EPS)
    d2 = knn.dist[:, 1].clamp_min(RATIO_EPS)
    return 1.0 - d1 / d2


def mutual_filter(
    corr: Correspondences, nn_tgt_of_src: torch.Tensor, nn_src_of_tgt: torch.Tensor
) -> Correspondences:
    """Keep only the correspondences that are mutual nearest neighbours.

    Objective: keep row ``i`` when ``nn_tgt_of_src[src_idx[i]] == tgt_idx[i]`` and
    ``nn_src_of_tgt[tgt_idx[i]] == src_idx[i]`` (the classical baselines' mutual check).

    Args:
        corr: correspondences to filter.
        nn_tgt_of_src: ``(N,)`` int64, the nearest target neighbour of each source point
            (``feature_knn(feats_src, feats_tgt, 1).idx[:, 0]``).
        nn_src_of_tgt: ``(M,)`` int64, the nearest source neighbour of each target point.

    Returns:
        The kept rows of ``corr``, in their original order.

    Raises:
        ShapeError: the neighbour tables are not 1-D.
    """
    if nn_tgt_of_src.ndim != 1 or nn_src_of_tgt.ndim != 1:
        raise ShapeError("nn_tgt_of_src and nn_src_of_tgt must be 1-D index tensors")
    if corr.src_idx.numel() == 0:
        return corr
    keep = (nn_tgt_of_src[corr.src_idx] == corr.tgt_idx) & (
        nn_src_of_tgt[corr.tgt_idx] == corr.src_idx
    )
    return Correspondences(corr.src_idx[keep], corr.tgt_idx[keep], corr.weight[keep])


def ratio_test_correspondences(
    feats_src: torch.Tensor,
    feats_tgt: torch.Tensor,
    k: int = 200,
    chunk_size: int | None = None,
    mutual: bool = False,
    parallel: Callable[[Sequence[Callable[[], KNN]]], list[KNN]] | None = None,
) -> Correspondences:
    """Bidirectional Lowe-ratio correspondences (the paper's section 3.1, Correspondence
    estimation).

    Objective: for every source point its two nearest target neighbours in feature space
    and for every target point its two nearest source neighbours; the match is the first
    neighbour, weighted by ``w = 1 - D(nn1) / D(nn2)`` (distances clamped at ``1e-9``), so
    ``w`` is in ``[0, 1]``. The ``k`` rows with the largest weight are kept in each direction
    (``min(k, N) + min(k, M)`` rows). No threshold and no deduplication: a mutual pair can
    appear once per direction.

    Args:
        feats_src: ``(N, C)`` unit source features.
        feats_tgt: ``(M, C)`` unit target features.
        k: rows kept per direction (>= 0); 200 in the paper.
        chunk_size: query rows per chunk of :func:`feature_knn` (``None``: automatic).
        mutual: keep only mutual nearest neighbours (before the top-``k`` selection).
        parallel: runs the two directions' neighbour searches (a list of calls, results in
            order), e.g. side by side on two threads (:func:`byoc_cli.threads.side_by_side`);
            None: one after the other. The result is the same.

    Returns:
        :class:`Correspondences`, rows of the source -> target direction first (by
        decreasing weight), then target -> source. ``weight`` carries gradients to both
        feature sets. Typed empty result (int64 indices, float weights, zero rows) when a
        cloud has fewer than 2 points (with a warning) or ``k == 0``.

    Raises:
        ShapeError: inputs are not 2-D floating tensors with the same channel count.
        ValueError: ``k < 0``.
    """
    _check_pair(feats_src, feats_tgt, "feats_src", "feats_tgt")
    if k < 0:
        raise ValueError(f"k must be >= 0, got {k}")
    n, m = feats_src.shape[0], feats_tgt.shape[0]
    if n < 2 or m < 2:
        warnings.warn(
            f"ratio test needs at least 2 points per cloud, got {n} and {m}; no correspondences",
            UserWarning,
            stacklevel=2,
        )
        return _empty(feats_src, feats_tgt)
    if k == 0:
        return _empty(feats_src, feats_tgt)

    knn_st, knn_ts = (parallel or _one_by_one)(
        [
            lambda: feature_knn(feats_src, feats_tgt, k=2, chunk_size=chunk_size),  # (N, 2)
            lambda: feature_knn(feats_tgt, feats_src, k=2, chunk_size=chunk_size),  # (M, 2)
        ]
    )
    w_st = _ratio_weight(knn_st)
    w_ts = _ratio_weight(knn_ts)
    src_st = torch.arange(n, device=feats_src.device)
    tgt_st = knn_st.idx[:, 0]
    tgt_ts = torch.arange(m, device=feats_src.device)
    src_ts = knn_ts.idx[:, 0]

    if mutual:
        keep_st = knn_ts.idx[tgt_st, 0] == src_st
        keep_ts = knn_st.idx[src_ts, 0] == tgt_ts
        src_st, tgt_st, w_st = src_st[keep_st], tgt_st[keep_st], w_st[keep_st]
        src_ts, tgt_ts, w_ts = src_ts[keep_ts], tgt_ts[keep_ts], w_ts[keep_ts]

    top_st = torch.topk(w_st.detach(), min(k, w_st.shape[0]), sorted=True).indices
    top_ts = torch.topk(w_ts.detach(), min(k, w_ts.shape[0]), sorted=True).indices
    return Correspondences(
        src_idx=torch.cat([src_st[top_st], src_ts[top_ts]]),
        tgt_idx=torch.cat([tgt_st[top_st], tgt_ts[top_ts]]),
        weight=torch.cat([w_st[top_st], w_ts[top_ts]]),
    )
