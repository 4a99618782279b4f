"""Voxel-grid neighbourhoods in plain PyTorch: cell averages, cell keys, near points.

What the multiscale refinement needs without a k-d tree (and without importing open3d,
whose import alone takes longer than the refinement): clouds thinned to one average point
per voxel (their normals: :mod:`byoc_cli.geometry.normals`), and, for moving query points,
the nearest points of a cloud among those in the cells around them.

Cells are ``floor((p - origin) / size)`` with the origin on the cloud's lowest cell corner
(a multiple of ``size``), so georeferenced coordinates (hundreds of kilometres) lose nothing;
a cell's key packs its three indices into one int64 (:data:`CELL_LIMIT` cells either side
of the origin per axis). Shapes: points ``(N, 3)`` float64 metres; indices int64.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.voxel import voxel_keys

#: cells per axis either side of the origin that a key can hold (2^20 cells of 1 cm: 10 km)
CELL_LIMIT = 1 << 20


def cell_keys(cells: torch.Tensor) -> torch.Tensor:
    """One int64 key per cell of ``cells (N, 3)`` int64 (the packing of
    :func:`byoc_cli.geometry.voxel.voxel_keys`): keys order x, then y, then z, and cells
    next to each other along z have consecutive keys.

    Raises:
        ValueError: a cell index is :data:`CELL_LIMIT` or more away from the origin (the
            cloud is too large for the cell size).
    """
    try:
        return voxel_keys(cells)
    except ShapeError as exc:
        raise ValueError(f"cloud spans more than {CELL_LIMIT} cells from the origin") from exc


def grid_origin(points: torch.Tensor, size: float) -> torch.Tensor:
    """``(3,)`` the lowest cell corner of ``points (N, 3)`` on the grid of ``size`` through 0
    (zeros for no points)."""
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ShapeError(f"points must be (N, 3), got {tuple(points.shape)}")
    if len(points) == 0:
        return points.new_zeros(3)
    return torch.floor(points.min(dim=0).values / size) * size


def _cells(points: torch.Tensor, size: float, origin: torch.Tensor) -> torch.Tensor:
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ShapeError(f"points must be (N, 3), got {tuple(points.shape)}")
    return (points - origin).div_(size).floor_().to(torch.int64)


def neighbor_positions(
    sorted_keys: torch.Tensor, cells: torch.Tensor, reach: int = 1
) -> torch.Tensor:
    """Where the cells within ``reach`` cells (per axis) of each of ``cells (Q, 3)`` are in
    ``sorted_keys (C,)`` (unique, ascending): ``(Q, (2 reach + 1)^3)`` int64 positions, -1 for
    empty cells, in the order of the offsets ``(dx, dy, dz)`` with dz fastest.

    Cells next to each other along z have consecutive keys, so one search per (x, y) column
    (9, not 27, for reach 1) finds the whole run: the keys ``base - reach .. base + reach``
    can only sit in the ``2 reach + 1`` places from where ``base - reach`` would go, and the
    key found at each place says which of them it is.

    Raises:
        ValueError: a column of a query lies :data:`CELL_LIMIT` or more from the origin.
    """
    width = 2 * reach + 1
    Q, C = len(cells), len(sorted_keys)
    if C == 0 or Q == 0:
        return torch.full((Q, width**3), -1, dtype=torch.int64)
    span = torch.arange(-reach, reach + 1)
    dx, dy = (d.reshape(-1) for d in torch.meshgrid(span, span, indexing="ij"))
    margin = torch.tensor([reach, reach, 0])
    cell_keys(torch.stack([cells.min(dim=0).values - margin, cells.max(dim=0).values + margin]))
    # a key is x * 2^42 + y * 2^21 + z (each offset into [0, 2^21)): neighbours add offsets
    base = cell_keys(cells)[:, None] + ((dx << 42) + (dy << 21))  # (Q, columns)
    low = torch.searchsorted(sorted_keys, base - reach)
    at = (low[:, :, None] + torch.arange(width)).clamp_max(C - 1)  # (Q, columns, width)
    dz = sorted_keys[at] - base[:, :, None] + reach  # the z offset a place holds, if in range
    dz = torch.where((dz >= 0) & (dz < width), dz, width)  # else: a slot that is dropped
    out = torch.full((Q, len(dx), width + 1), -1, dtype=torch.int64)
    out.scatter_(2, dz, at)  # keys are unique: a place fills at most one slot
    return out[:, :, :width].reshape(Q, -1)


def voxel_average(points: torch.Tensor, size: float) -> torch.Tensor:
    """The average of the points in each occupied cell of ``size``: ``(K, 3)``, in key order.

    Args:
        points: ``(N, 3)`` points.
        size: cell edge (metres).
    """
    return voxel_means(points, size)[0]


def voxel_means(
    points: torch.Tensor, size: float, weights: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The weighted average of the points in each occupied cell of ``size``, and the cell's
    total weight: ``(K, 3)`` and ``(K,)``, in key order. Averages of averages with their
    weights (their point counts) are a coarser level of a pyramid built from a finer one.

    Args:
        points: ``(N, 3)`` points.
        size: cell edge (metres).
        weights: ``(N,)`` positive weights; None: 1 each (the weights out are the counts).
    """
    keys = cell_keys(_cells(points, size, grid_origin(points, size)))
    uniq, inverse = torch.unique(keys, return_inverse=True)
    sums = torch.zeros(len(uniq), 3, dtype=points.dtype)
    if weights is None:
        sums.index_add_(0, inverse, points)
        total = torch.bincount(inverse, minlength=len(uniq)).to(points.dtype)
    else:
        sums.index_add_(0, inverse, points * weights[:, None])
        total = torch.zeros(len(uniq), dtype=points.dtype).index_add_(0, inverse, weights)
    return sums / total[:, None], total


#: most cells (padding included) a :class:`DenseCells` table may have: 16 MB of int32
DENSE_CELLS = 1 << 22


class DenseCells(NamedTuple):
    """A dense table over the box of a set of occupied cells: one int32 value per cell of the
    box (-1 for empty cells), padded by ``2 reach`` cells on each side, z fastest.

    Built by :meth:`build`; :meth:`lookup` gives what :func:`neighbor_positions` gives (with
    the values in place of the positions) with one gather instead of binary searches.
    """

    low: torch.Tensor  # (3,) int64, the cell of table index 0
    dims: torch.Tensor  # (3,) int64, cells of the box per axis
    table: torch.Tensor  # (prod(dims),) int32
    reach: int  # the largest reach the padding allows
    empty: int = -1  # the value of empty cells

    @staticmethod
    def build(
        cells: torch.Tensor, values: torch.Tensor, reach: int, empty: int = -1
    ) -> DenseCells | None:
        """The table of ``values (C,)`` at distinct ``cells (C, 3)`` int64, ``empty`` in the
        other cells, for searches of up to ``reach``; None when the box has more than
        :data:`DENSE_CELLS` cells or a value does not fit in int32."""
        pad = 2 * reach
        low = cells.min(dim=0).values - pad
        dims = cells.max(dim=0).values + pad - low + 1
        size = math.prod(int(d) for d in dims)
        if size > DENSE_CELLS or max(int(values.max()), empty) >= 2**31:
            return None
        table = torch.full((size,), empty, dtype=torch.int32)
        table[_linear(cells - low, dims)] = values.to(torch.int32)
        return DenseCells(low, dims, table, reach, empty)

    def lookup(self, cells: torch.Tensor, reach: int) -> torch.Tensor:
        """``(Q, (2 reach + 1)^3)`` int64 values of the cells within ``reach`` of each of
        ``cells (Q, 3)``, in the order of :func:`neighbor_positions` (:attr:`empty` for an
        empty cell)."""
        if reach > self.reach:
            raise ValueError(f"the table is padded for reach {self.reach}, not {reach}")
        span = torch.arange(-reach, reach + 1)
        offsets = torch.cartesian_prod(span, span, span)  # (dx, dy, dz), dz fastest
        rel = cells - self.low
        # every occupied cell lies 2 reach cells inside the box: a query cell closer than
        # reach to its edge (or outside) has none around it
        inside = ((rel >= reach) & (rel < self.dims - reach)).all(dim=1)
        rel = torch.minimum(rel.clamp_min(reach), self.dims - 1 - reach)
        at = _linear(rel, self.dims)[:, None] + _linear(offsets, self.dims)
        out = self.table.index_select(0, at.reshape(-1)).view(at.shape).to(torch.int64)
        return out.masked_fill_(~inside[:, None], self.empty)


def _linear(cells: torch.Tensor, dims: torch.Tensor) -> torch.Tensor:
    """Row-major (z fastest) index of ``cells (Q, 3)`` in a box of ``dims (3,)``."""
    return (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]


#: most points one cell of a :class:`CellIndex` may hold: its searches size every query by
#: the fullest cell, so it is for voxel averages (one point per cell; the refinement's
#: levels), not for raw scans (a spinning LiDAR puts thousands of returns into one cell
#: near its sensor: a k-d tree answers those, :mod:`byoc_cli.geometry.sampling`)
MAX_PER_CELL = 64


class CellIndex:
    """The points of a cloud by cell: sorted keys and, per key, the points in that cell.

    Args:
        points: ``(N, 3)`` points.
        size: cell edge (metres).
        dense_reach: also build a :class:`DenseCells` table for searches of up to this
            reach, when its box has at most :data:`DENSE_CELLS` cells (a search is then one
            lookup per neighbour cell instead of a binary search per column; the results
            are the same).
        origin: ``(3,)`` the grid's origin, a cell corner at or below every point (default:
            :func:`grid_origin` of ``points``): an index of part of a cloud on the cloud's grid.
        max_per_cell: refuse clouds with a cell fuller than this (None: any).

    Raises:
        ValueError: a cell holds more than ``max_per_cell`` points.
    """

    def __init__(
        self,
        points: torch.Tensor,
        size: float,
        dense_reach: int | None = None,
        origin: torch.Tensor | None = None,
        max_per_cell: int | None = MAX_PER_CELL,
    ) -> None:
        self.points = points
        self.size = float(size)
        self.origin = grid_origin(points, size) if origin is None else origin
        # (3, N + 1) float32 offsets from the origin, for distances; column N is a point at
        # infinity that stands for "no point" (its distance to anything is inf)
        self.none = len(points)
        self.columns = torch.cat(
            [(points - self.origin).T.to(torch.float32), torch.full((3, 1), float("inf"))], 1
        ).contiguous()
        keys = cell_keys(_cells(points, size, self.origin))
        self.order = torch.argsort(keys, stable=True)  # (N,) points sorted by cell
        sorted_keys = keys[self.order]
        self.keys, counts = torch.unique_consecutive(sorted_keys, return_counts=True)
        self.start = torch.cumsum(counts, 0) - counts  # (C,) first position in `order`
        self.first = self.order[self.start]  # (C,) the first point of each cell
        self.count = counts  # (C,)
        self.max_count = int(counts.max()) if len(counts) else 0
        if max_per_cell is not None and self.max_count > max_per_cell:
            raise ValueError(
                f"a cell of {size:g} holds {self.max_count} points (at most {max_per_cell}): "
                "index voxel averages, or search with a k-d tree"
            )
        self.dense: DenseCells | None = None
        if dense_reach is not None and len(self.keys):
            # one point per cell: the table holds the point itself (none: the point at
            # infinity), else the cell's position (none: -1)
            one = self.max_count <= 1
            values = self.first if one else torch.arange(len(self.keys))
            cells = _cells(points[self.first], size, self.origin)
            self.dense = DenseCells.build(cells, values, dense_reach, self.none if one else -1)

    def around(self, queries: torch.Tensor, reach: int = 1) -> torch.Tensor:
        """Indices of the points in the cells within ``reach`` cells of each query's,
        ``(Q, (2 reach + 1)^3 m)`` int64, -1 padded (``m`` the most points in one cell).
        Every point within ``reach * size`` of a query is among them.

        Args:
            queries: ``(Q, 3)`` points.
            reach: cells per axis either side.
        """
        found = self._around(queries, reach)
        return found.masked_fill_(found == self.none, -1)

    def _around(self, queries: torch.Tensor, reach: int) -> torch.Tensor:
        """:meth:`around` padded with :attr:`none` (the point at infinity) instead of -1."""
        cells = _cells(queries, self.size, self.origin)
        if self.dense is not None and reach <= self.dense.reach:
            pos = self.dense.lookup(cells, reach)
            if self.max_count <= 1:  # the table holds the points themselves
                return pos
        else:
            pos = neighbor_positions(self.keys, cells, reach)
        if self.max_count <= 1:  # one point per cell (voxel averages at the cell size)
            return torch.where(pos >= 0, self.first[pos.clamp_min(0)], self.none)
        found = pos >= 0
        safe = pos.clamp_min(0)
        start, count = self.start[safe], torch.where(found, self.count[safe], 0)
        slots = torch.arange(max(self.max_count, 1))
        at = start[..., None] + slots  # (Q, 27, m)
        valid = slots < count[..., None]
        index = self.order[at.clamp_max(len(self.order) - 1).clamp_min(0)]
        return torch.where(valid, index, self.none).reshape(len(queries), -1)


def _distance2(cells: CellIndex, index: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """``(Q, k)`` float32 squared distances from ``queries (Q, 3)`` to the points ``index
    (Q, k)`` of ``cells`` (``cells.none``, the point at infinity: inf), in place one
    coordinate at a time (float64 temporaries of this size cost ten times as much on a
    CPU)."""
    flat = index.reshape(-1)
    q = (queries - cells.origin).T.to(torch.float32)
    d2 = cells.columns[0].index_select(0, flat).view(index.shape).sub_(q[0][:, None]).square_()
    for axis in (1, 2):
        d2 += (
            cells.columns[axis]
            .index_select(0, flat)
            .view(index.shape)
            .sub_(q[axis][:, None])
            .square_()
        )
    return d2


def nearest_candidates(
    index: CellIndex, queries: torch.Tensor, k: int, reach: int = 1
) -> torch.Tensor:
    """The ``k`` points of ``index`` nearest each query among the cells within ``reach``,
    nearest first, ``(Q, k)`` int64 (-1 where there are fewer)."""
    cand = index._around(queries, reach)
    d2 = _distance2(index, cand, queries)
    near, pick = smallest(d2, min(k, cand.shape[1]))
    chosen = cand.gather(1, pick)
    return chosen.masked_fill_(~torch.isfinite(near), -1)


def smallest(values: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` smallest of each row of ``values (Q, m)`` (CPU, ``1 <= k <= m``), ascending:
    ``(Q, k)`` values and ``(Q, k)`` int64 columns. ``torch.topk``'s result up to the order of
    equal values, by numpy's partition: on rows of 27 to 125 about three times faster on the
    CPU."""
    v = values.numpy()
    if k == 1:
        pick = v.argmin(axis=1)[:, None]
    else:
        part = np.argpartition(v, k - 1, axis=1)[:, :k] if k < v.shape[1] else None
        if part is None:
            part = np.broadcast_to(np.arange(v.shape[1]), v.shape)
        order = np.argsort(np.take_along_axis(v, part, axis=1), axis=1, kind="stable")
        pick = np.take_along_axis(part, order, axis=1)
    pick = pick.astype(np.int64, copy=False)
    return torch.from_numpy(np.take_along_axis(v, pick, axis=1)), torch.from_numpy(pick)


class Nearest(NamedTuple):
    """Nearest of the candidates: ``index (Q,)`` int64 (-1: none) and ``distance2 (Q,)``."""

    index: torch.Tensor
    distance2: torch.Tensor


def nearest_of(
    index: CellIndex,
    queries: torch.Tensor,
    candidates: torch.Tensor,
    coordinates: torch.Tensor | None = None,
) -> Nearest:
    """For each of ``queries (Q, 3)``, the nearest of its ``candidates (Q, k)`` (indices into
    ``index.points``, -1 = none); ``distance2`` float32. ``coordinates``: the candidates'
    :func:`candidate_coordinates`, for queries that move while their candidates stay (the
    same result without gathering them again)."""
    if coordinates is None:
        coordinates = candidate_coordinates(index, candidates)
    q = (queries - index.origin).T.to(torch.float32)
    d2 = (coordinates[0] - q[0][:, None]).square_()
    for axis in (1, 2):  # the arithmetic of _distance2, in its order
        d2 += (coordinates[axis] - q[axis][:, None]).square_()
    best, pick = d2.min(dim=1)
    return Nearest(candidates.gather(1, pick[:, None])[:, 0], best)


def nearest_of_arrays(
    moved: np.ndarray, origin: np.ndarray, candidates: np.ndarray, coordinates: np.ndarray
) -> Nearest:
    """:func:`nearest_of` in numpy, the same arithmetic (the refinement's steps, which run in
    numpy): for each of ``moved (Q, 3)``, the nearest of its ``candidates (Q, k)`` whose
    ``coordinates (3, Q, k)`` float32 (:func:`candidate_coordinates`) are offsets from
    ``origin (3,)``; numpy arrays."""
    q = (moved - origin).T.astype(np.float32)
    d2 = np.square(coordinates[0] - q[0][:, None])
    for axis in (1, 2):
        d2 += np.square(coordinates[axis] - q[axis][:, None])
    pick = d2.argmin(axis=1)[:, None]
    return Nearest(
        np.take_along_axis(candidates, pick, 1)[:, 0], np.take_along_axis(d2, pick, 1)[:, 0]
    )


def candidate_coordinates(index: CellIndex, candidates: torch.Tensor) -> torch.Tensor:
    """``(3, Q, k)`` float32 offsets from ``index.origin`` of the points ``candidates (Q, k)``
    (-1: the point at infinity), for :func:`nearest_of`."""
    flat = torch.where(candidates < 0, index.none, candidates).reshape(-1)
    return index.columns.index_select(1, flat).view(3, *candidates.shape)
