"""How a cloud is sampled, without knowing its units: point spacing and size.

What ``--voxel-size auto`` reads from the data (:mod:`byoc_cli.pipeline.scale`): the median
distance from a point to its nearest neighbour (the sampling step of the scan) and the median
distance of the points from their coordinate-wise median (the scan's size), both in the units
of the points. Shapes: points ``(N, 3)``, float; results are plain floats.
"""

from __future__ import annotations

from typing import NamedTuple

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


#: a cloud whose median point lies farther than this many radii from the origin is
#: registered about its median point (georeferenced scans: hundreds of kilometres away)
FAR_RADII = 100.0
#: points farther than this many radii from the median point are strays, left out of the
#: registration (a spinning LiDAR's farthest returns lie within about 20 radii)
STRAY_RADII = 1000.0


class LocalFrame(NamedTuple):
    """Where a cloud is registered: its points minus ``origin``, the strays left out.

    Attributes:
        origin: ``(3,)`` float64 subtracted from the input coordinates (the median point of
            a cloud far from the origin, else zeros: nothing moves).
        inside: ``(N,)`` bool, the points within :data:`STRAY_RADII` radii of the median
            point; None when that is all of them.
        radius: :func:`cloud_radius` of the points.
    """

    origin: np.ndarray
    inside: np.ndarray | None
    radius: float

    @property
    def strays(self) -> int:
        """Points left out as strays."""
        return 0 if self.inside is None else int((~self.inside).sum())

    @property
    def moved(self) -> bool:
        """Whether the cloud is registered about another origin than its own."""
        return bool(self.origin.any())

    def local(self, points: np.ndarray) -> np.ndarray:
        """``(K, 3)`` float64 local coordinates of the inside points of ``points (N, 3)``
        (the array itself when nothing moves and nothing is left out). The median point is
        a point of the cloud's box: near points subtract without rounding (Sterbenz)."""
        kept = points if self.inside is None else points[self.inside]
        return kept - self.origin if self.moved else kept


def local_frame(points: np.ndarray) -> LocalFrame:
    """The :class:`LocalFrame` of ``points (N, 3)`` float64 (finite). O(N)."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points must be (N, 3), got {tuple(points.shape)}")
    zero = np.zeros(3)
    if len(points) < 2:
        return LocalFrame(zero, None, 0.0)
    centre = np.median(points, axis=0)
    with np.errstate(over="ignore", invalid="ignore"):
        distance = np.linalg.norm(points - centre, axis=1)
    radius = float(np.median(distance))
    if not radius > 0 or not np.isfinite(radius):
        return LocalFrame(zero, None, radius)
    origin = centre if np.abs(centre).max() > FAR_RADII * radius else zero
    inside = distance <= STRAY_RADII * radius
    return LocalFrame(origin, None if inside.all() else inside, radius)
