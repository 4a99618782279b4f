"""How a cloud is sampled, without knowing its units: point spacing and size.

What ``--voxel-size auto`` reads from the data (:mod:`byoc_cli.pipeline.scale`): the median
distance from a point to its nearest neighbour (the sampling step of the scan) and the median
distance of the points from their coordinate-wise median (the scan's size), both in the units
of the points. Shapes: points ``(N, 3)``, float; results are plain floats.
"""

from __future__ import annotations

import numpy as np
import torch

from byoc_cli.errors import ShapeError

#: query points whose nearest neighbour is measured (a seeded random subset)
SPACING_SAMPLES = 2048
#: neighbours asked per query: a query with this many copies of itself (a scanner's repeated
#: returns at the sensor) is asked again among the distinct points
SPACING_NEIGHBOURS = 8


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
) -> float:
    """Median nearest-neighbour distance of ``points (N, 3)``: the sampling step of a scan.

    Measured for a seeded random subset of ``samples`` query points against the whole cloud
    with a k-d tree (``pykdtree``; ``benchmarks/kdtree.py`` measures it against SciPy's and
    Open3D's): O(N log N) time and O(N) memory however unevenly the points are spread (a
    spinning LiDAR puts thousands of returns near its sensor and a few far away). Duplicate
    points (distance 0) are left out: a query with :data:`SPACING_NEIGHBOURS` or more copies
    of itself is asked again among the distinct points. Returns 0.0 when the cloud has fewer
    than 2 distinct points.

    Args:
        points: ``(N, 3)``, finite.
        generator: draws the query subset (default: seed 0).
        samples: query points at most.
    """
    from pykdtree.kdtree import KDTree

    _check(points)
    pts = np.ascontiguousarray(points.detach().cpu().numpy(), dtype=np.float64)
    n = len(pts)
    if n < 2:
        return 0.0
    generator = generator or torch.Generator().manual_seed(0)
    asked = pts[torch.randperm(n, generator=generator)[: min(samples, n)].numpy()]
    dist, _ = KDTree(pts).query(asked, k=min(SPACING_NEIGHBOURS, n))
    dist = np.where(dist > 0, dist, np.inf).min(axis=1)
    stuck = ~np.isfinite(dist)
    if stuck.any():
        distinct = np.unique(pts, axis=0)
        if len(distinct) < 2:
            return 0.0
        dist[stuck] = KDTree(distinct).query(asked[stuck], k=2)[0][:, 1]
    return float(np.median(dist))
