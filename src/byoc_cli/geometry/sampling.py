"""How a cloud is sampled, without knowing its units: point spacing and size.

What ``--voxel-size auto`` reads from the data (:mod:`byoc_cli.pipeline.scale`): the median
distance from a point to its nearest neighbour (the sampling step of the scan) and the median
distance of the points from their coordinate-wise median (the scan's size), both in the units
of the points. Shapes: points ``(N, 3)``, float; results are plain floats.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.neighbors import (
    CellIndex,
    _cells,
    cell_keys,
    grid_origin,
    nearest_candidates,
)

#: query points whose nearest neighbour is measured (a seeded random subset)
SPACING_SAMPLES = 2048
#: the first search cell is ``2 radius / sqrt(N)`` (about the spacing of N points spread
#: over a surface of the cloud's size); doubled for the queries that found no neighbour
#: within reach, at most :data:`SPACING_ROUNDS` times
SPACING_ROUNDS = 24


def _check(points: torch.Tensor) -> None:
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points must be (N, 3), got {tuple(points.shape)}")


def cloud_radius(points: torch.Tensor) -> float:
    """Median distance of ``points (N, 3)`` from their coordinate-wise median (0.0 for fewer
    than 2 points): the size of a scan, robust to a few stray points far away."""
    _check(points)
    if len(points) < 2:
        return 0.0
    pts = points.to(torch.float64)
    centre = pts.median(dim=0).values
    return float(np.median(torch.linalg.vector_norm(pts - centre, dim=1).numpy()))


def nearest_spacing(
    points: torch.Tensor,
    generator: torch.Generator | None = None,
    samples: int = SPACING_SAMPLES,
    radius: float | None = None,
) -> float:
    """Median nearest-neighbour distance of ``points (N, 3)``: the sampling step of a scan.

    Measured for a seeded random subset of ``samples`` query points against the whole cloud
    on a cell grid that starts at ``2 radius / sqrt(N)`` and doubles for the queries that found
    no other point within reach. Duplicate points (distance 0) are left
    out. Returns 0.0 when the cloud has fewer than 2 distinct points.

    Args:
        points: ``(N, 3)``.
        generator: draws the query subset (default: seed 0).
        samples: query points at most.
        radius: :func:`cloud_radius` of ``points`` if known (it sets the first cell).
    """
    _check(points)
    pts = points.to(torch.float64)
    n = len(pts)
    radius = cloud_radius(pts) if radius is None else radius
    if n < 2 or radius <= 0:
        return 0.0
    generator = generator or torch.Generator().manual_seed(0)
    queries = torch.randperm(n, generator=generator)[: min(samples, n)]
    found = torch.full((len(queries),), float("inf"), dtype=torch.float64)
    todo = torch.arange(len(queries))
    cell = 2.0 * radius / math.sqrt(n)
    for _ in range(SPACING_ROUNDS):
        asked = pts[queries[todo]]
        index = _index_around(pts, asked, cell)
        near = nearest_candidates(index, asked, k=16)  # (Q, 16), self included
        valid = near >= 0
        dist = torch.linalg.vector_norm(index.points[near.clamp_min(0)] - asked[:, None], dim=2)
        dist = dist.masked_fill(~valid | (dist <= 0), float("inf")).min(dim=1).values
        hit = dist <= cell  # within reach of one cell: the true nearest neighbour
        found[todo[hit]] = dist[hit]
        todo = todo[~hit]
        if len(todo) == 0:
            break
        cell *= 2
    finite = found[torch.isfinite(found)]
    return float(np.median(finite.numpy())) if len(finite) else 0.0


def _index_around(points: torch.Tensor, queries: torch.Tensor, cell: float) -> CellIndex:
    """A :class:`CellIndex` at ``cell`` of the ``points (N, 3)`` in the 27 cells around each of
    ``queries (Q, 3)``, on the grid of the whole cloud: around the queries it holds what the
    index of every point holds, in the same order, and costs a pass over the points instead
    of a sort of them."""
    origin = grid_origin(points, cell)
    span = torch.arange(-1, 2)
    offsets = torch.cartesian_prod(span, span, span)  # (27, 3)
    asked = _cells(queries, cell, origin)
    wanted = torch.unique(cell_keys((asked[:, None, :] + offsets).reshape(-1, 3)))
    keys = cell_keys(_cells(points, cell, origin))
    at = torch.searchsorted(wanted, keys).clamp_max(len(wanted) - 1)
    return CellIndex(points[wanted[at] == keys], cell, origin=origin)
