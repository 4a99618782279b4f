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
    c = coords + offset
    if bool(((c < 0) | (c >= (1 << 21))).any()):
        raise ShapeError("voxel coordinates out of range (cloud too large for this voxel size)")
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


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
