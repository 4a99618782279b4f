"""Voxelisation that keeps the first point per voxel, with a strict voxel <-> point map."""

from __future__ import annotations

from typing import NamedTuple

import torch

from byoc_cli.errors import ShapeError


class VoxelGrid(NamedTuple):
    """Result of :func:`voxelize`.

    Attributes:
        coords: ``(M, 3)`` int64 integer voxel coordinates ``floor(xyz / voxel_size)``,
            one row per occupied voxel, in the order of their first point.
        point_index: ``(M,)`` int64; ``point_index[m] = i`` means voxel ``m`` keeps the
            input point ``points[i]`` (the first point that fell into it). Increasing.
        voxel_of_point: ``(N,)`` int64; ``voxel_of_point[i] = m`` means input point ``i``
            lies in voxel ``m``. ``voxel_of_point[point_index] == arange(M)``.
    """

    coords: torch.Tensor
    point_index: torch.Tensor
    voxel_of_point: torch.Tensor


def voxel_keys(coords: torch.Tensor) -> torch.Tensor:
    """Pack ``(M, 3)`` int64 voxel coordinates into unique int64 keys (21 bits per axis).

    Coordinates must lie in ``[-2**20, 2**20)``; that is +-26 km at 2.5 cm.
    """
    offset = 1 << 20
    if coords.numel():
        low, high = torch.aminmax(coords)  # one pass instead of a mask per bound
        if int(low) < -offset or int(high) >= offset:
            raise ShapeError("voxel coordinates out of range (cloud too large for this voxel size)")
    x, y, z = (coords + offset).unbind(dim=1)
    keys = x << 42
    keys |= y << 21
    keys |= z
    return keys


def voxelize(points: torch.Tensor, voxel_size: float) -> VoxelGrid:
    """Quantise points to voxels of side ``voxel_size``, keeping the first point per voxel.

    Args:
        points: ``(N, 3)`` float points.
        voxel_size: edge length, in the units of ``points`` (> 0).

    Returns:
        :class:`VoxelGrid` (empty tensors when ``N == 0``).

    Raises:
        ShapeError: wrong shape, non-positive voxel size, or coordinates too far from the
            origin for 21-bit voxel indices.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points must have shape (N, 3), got {tuple(points.shape)}")
    if not voxel_size > 0:
        raise ShapeError(f"voxel_size must be > 0, got {voxel_size}")
    device = points.device
    n = points.shape[0]
    coords = torch.floor(points.to(torch.float64) / voxel_size).to(torch.int64)
    if n == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        return VoxelGrid(coords.reshape(0, 3), empty, empty)
    keys = voxel_keys(coords)
    uniq, inverse = torch.unique(keys, return_inverse=True)
    # first point of each voxel: the minimum index among the points mapped to it
    first = torch.full((uniq.shape[0],), n, dtype=torch.int64, device=device)
    first.scatter_reduce_(0, inverse, torch.arange(n, device=device), reduce="amin")
    # order voxels by their first point so the kept points keep the input order
    order = torch.argsort(first)
    point_index = first[order]
    rank = torch.empty_like(order)
    rank[order] = torch.arange(order.shape[0], device=device)
    voxel_of_point = rank[inverse]
    return VoxelGrid(coords[point_index], point_index, voxel_of_point)


def _neighbour_offsets(device: torch.device) -> torch.Tensor:
    r = torch.arange(-1, 2, device=device)
    return torch.cartesian_prod(r, r, r)


def near_occupied(
    points_query: torch.Tensor, points_ref: torch.Tensor, cell: float
) -> torch.Tensor:
    """Which query points lie in or next to a cell occupied by a reference point.

    Both clouds are quantised at ``cell``; a query point counts when one of the 27 cells
    around its own holds a reference point, i.e. it has a reference point within at most
    ``2 * sqrt(3) * cell`` and every point within ``cell`` is found. Runs in
    O((N + M) log M) with sorted keys, no pairwise distances.

    Args:
        points_query: ``(N, 3)``.
        points_ref: ``(M, 3)``.
        cell: cell size (> 0).

    Returns:
        ``(N,)`` bool.
    """
    if points_query.shape[0] == 0 or points_ref.shape[0] == 0:
        return torch.zeros(points_query.shape[0], dtype=torch.bool, device=points_query.device)
    q = torch.floor(points_query.to(torch.float64) / cell).to(torch.int64)
    r = torch.floor(points_ref.to(torch.float64) / cell).to(torch.int64)
    ref_keys = torch.unique(voxel_keys(r))
    hit = torch.zeros(q.shape[0], dtype=torch.bool, device=q.device)
    for offset in _neighbour_offsets(q.device):
        keys = voxel_keys(q + offset)
        pos = torch.searchsorted(ref_keys, keys).clamp_max(ref_keys.shape[0] - 1)
        hit |= ref_keys[pos] == keys
    return hit
