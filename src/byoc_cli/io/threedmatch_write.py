"""Writers of the 3DMatch ground-truth files read by :mod:`byoc_cli.io.threedmatch`.

``gt.log``
    Per pair a header line ``i j n`` (target fragment, source fragment, number of fragments),
    then the 4x4 ``T_tgt_src`` that maps the points of fragment ``j`` into fragment ``i``'s
    frame, one row per line.
``gt.info``
    Per pair the same header, then the 6x6 information matrix, one row per line; the
    convention is the official one (see :func:`byoc_cli.pipeline.fragments.information_matrix`).
``gt_overlap.log``
    Lines ``i,j,overlap`` (the Predator / 3DLoMatch format).

Numbers are written as the shortest decimal that reads back to the same float64, so
``read_gt_log(write_gt_log(...))`` returns the matrices bit for bit. Every file is written
atomically (:mod:`byoc_cli.io.atomic`).

Depends on numpy and :mod:`byoc_cli.errors` only.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from byoc_cli.errors import ShapeError
from byoc_cli.io.atomic import atomic_write_text

__all__ = [
    "format_gt_info",
    "format_gt_log",
    "format_gt_overlap",
    "write_gt_info",
    "write_gt_log",
    "write_gt_overlap",
]

#: Largest accepted ``max |R^T R - I|`` of a gt.log matrix to write (the reader's tolerance).
_ORTHONORMAL_TOL = 1e-3


def _check_pair(i: int, j: int, num_fragments: int) -> None:
    if i == j:
        raise ShapeError(f"pair of a fragment with itself ({i} {j})")
    if min(i, j) < 0 or max(i, j) >= num_fragments:
        raise ShapeError(f"pair {i} {j} out of range for {num_fragments} fragments")


def _check_pairs(
    pairs: Sequence[tuple[int, int]], matrices: Sequence[np.ndarray], num_fragments: int, size: int
) -> list[np.ndarray]:
    if len(pairs) != len(matrices):
        raise ShapeError(f"{len(pairs)} pairs but {len(matrices)} matrices")
    if len(set(pairs)) != len(pairs):
        raise ShapeError("a pair is listed twice")
    out = []
    for (i, j), matrix in zip(pairs, matrices, strict=True):
        _check_pair(int(i), int(j), int(num_fragments))
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.shape != (size, size):
            raise ShapeError(
                f"the matrix of pair {i} {j} must be ({size}, {size}), got {matrix.shape}"
            )
        if not np.all(np.isfinite(matrix)):
            raise ShapeError(f"the matrix of pair {i} {j} has NaN or Inf entries")
        out.append(matrix)
    return out


def _record(i: int, j: int, num_fragments: int, matrix: np.ndarray) -> str:
    rows = "".join(" ".join(repr(float(x)) for x in row) + "\n" for row in matrix)
    return f"{int(i)} {int(j)} {int(num_fragments)}\n{rows}"


def format_gt_log(
    pairs: Sequence[tuple[int, int]], transforms: Sequence[np.ndarray], num_fragments: int
) -> str:
    """The text of a ``gt.log``.

    Args:
        pairs: ``[(i, j)]``, target ``i`` and source ``j`` of each record, in file order.
        transforms: ``(4, 4)`` ``T_tgt_src`` per pair, mapping fragment ``j`` into ``i``.
        num_fragments: ``n`` of the headers (every ``i``, ``j`` is below it).

    Returns:
        The file's text (empty when there is no pair).

    Raises:
        ShapeError: counts differ, a pair repeats, pairs a fragment with itself or lies out of
            range, or a matrix is not a finite rigid 4x4 transform.
    """
    matrices = _check_pairs(pairs, transforms, num_fragments, 4)
    for (i, j), T in zip(pairs, matrices, strict=True):
        R = T[:3, :3]
        rigid = float(np.max(np.abs(R.T @ R - np.eye(3)))) <= _ORTHONORMAL_TOL
        if not rigid or np.linalg.det(R) < 0 or np.max(np.abs(T[3] - [0, 0, 0, 1])) > 1e-9:
            raise ShapeError(f"the matrix of pair {i} {j} is not a rigid transform")
    return "".join(
        _record(i, j, num_fragments, T) for (i, j), T in zip(pairs, matrices, strict=True)
    )


def format_gt_info(
    pairs: Sequence[tuple[int, int]], infos: Sequence[np.ndarray], num_fragments: int
) -> str:
    """The text of a ``gt.info`` (one 6x6 information matrix per pair).

    Raises:
        ShapeError: counts differ, a pair repeats or is invalid, a matrix is not finite 6x6.
    """
    matrices = _check_pairs(pairs, infos, num_fragments, 6)
    return "".join(
        _record(i, j, num_fragments, m) for (i, j), m in zip(pairs, matrices, strict=True)
    )


def format_gt_overlap(pairs: Sequence[tuple[int, int]], overlaps: Sequence[float]) -> str:
    """The text of a ``gt_overlap.log`` (lines ``i,j,overlap``).

    Raises:
        ShapeError: counts differ, or an overlap is not a finite number in [0, 1].
    """
    if len(pairs) != len(overlaps):
        raise ShapeError(f"{len(pairs)} pairs but {len(overlaps)} overlaps")
    lines = []
    for (i, j), overlap in zip(pairs, overlaps, strict=True):
        overlap = float(overlap)
        if not (math.isfinite(overlap) and 0.0 <= overlap <= 1.0):
            raise ShapeError(f"overlap of pair {i} {j} must lie in [0, 1], got {overlap}")
        lines.append(f"{int(i)},{int(j)},{overlap:.4f}\n")
    return "".join(lines)


def write_gt_log(
    path: str | os.PathLike[str],
    pairs: Sequence[tuple[int, int]],
    transforms: Sequence[np.ndarray],
    num_fragments: int,
) -> None:
    """Write a ``gt.log`` atomically (see :func:`format_gt_log`).

    Raises:
        ShapeError: invalid records (nothing is written).
        InputError: the file cannot be written.
    """
    atomic_write_text(path, format_gt_log(pairs, transforms, num_fragments))


def write_gt_info(
    path: str | os.PathLike[str],
    pairs: Sequence[tuple[int, int]],
    infos: Sequence[np.ndarray],
    num_fragments: int,
) -> None:
    """Write a ``gt.info`` atomically (see :func:`format_gt_info`).

    Raises:
        ShapeError: invalid records (nothing is written).
        InputError: the file cannot be written.
    """
    atomic_write_text(path, format_gt_info(pairs, infos, num_fragments))


def write_gt_overlap(
    path: str | os.PathLike[str], pairs: Sequence[tuple[int, int]], overlaps: Sequence[float]
) -> None:
    """Write a ``gt_overlap.log`` atomically (see :func:`format_gt_overlap`).

    Raises:
        ShapeError: invalid records (nothing is written).
        InputError: the file cannot be written.
    """
    atomic_write_text(path, format_gt_overlap(pairs, overlaps))
