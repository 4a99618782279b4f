"""How a cloud is sampled, without knowing its units: point spacing, size and scan lines.

What ``--voxel-size auto`` reads from the data (:mod:`byoc_cli.pipeline.scale`): the median
distance from a point to its nearest neighbour (the sampling step of the scan), the median
distance of the points from their coordinate-wise median (the scan's size), both in the units
of the points, the share of a voxel's kept points whose neighbourhood is a line (a scan
sampled along lines, such as a spinning LiDAR's rings, shows them where the voxel is smaller
than the gap between the lines) and the share whose neighbourhood is not a smooth surface (a
scan of a smooth free-form object has almost none). Shapes: points ``(N, 3)``, float; results
are plain floats.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.visibility import cube_bins

#: query points whose nearest neighbour is measured (a seeded random subset)
SPACING_SAMPLES = 2048
#: points per leaf of the spacing's k-d tree: a tree built for a few thousand queries is
#: built faster with larger leaves (16, pykdtree's default: 15.8 ms on a 230k-point depth
#: frame; 64: 10.9 ms; the same distances)
KDTREE_LEAF = 64
#: neighbours asked per query: a query with this many copies of itself (a scanner's repeated
#: returns at the sensor) is asked again among the distinct points
SPACING_NEIGHBOURS = 8
#: :func:`linear_share`: the neighbourhood of a kept point is the kept points within this many
#: voxels of it (at most :data:`LINE_NEIGHBOURS` of them, the point included) ...
LINE_RADIUS = 2.5
LINE_NEIGHBOURS = 32
#: ... it has a shape with at least this many points (fewer: an isolated point, not counted) ...
LINE_MIN_POINTS = 4
#: ... and is a line when its linearity ``(s1 - s2) / s1`` exceeds this (``s1 >= s2 >= s3``:
#: the standard deviations along its principal axes)
LINEARITY = 0.7
#: :func:`rough_share`: the neighbourhood of a kept point is its this many nearest kept points
#: (within :data:`ROUGH_RADIUS` voxels) ...
ROUGH_NEIGHBOURS = 64
ROUGH_RADIUS = 8.0
#: ... and is rough when its surface variation ``s3^2 / (s1^2 + s2^2 + s3^2)`` exceeds this
ROUGHNESS = 0.01
#: query points of :func:`rough_share` (a seeded random subset)
ROUGH_SAMPLES = 1024
#: :func:`even_radius`: the cloud is thinned to one point per cube of this share of its
#: radius, from at most :data:`EVEN_SAMPLES` of its points (every k-th) lying within
#: :data:`EVEN_REACH` radii of its median (stray points far away are left out)
EVEN_CELL = 1 / 30
EVEN_SAMPLES = 200_000
EVEN_REACH = 30.0
#: :func:`surround_share`: the directions from the origin binned on a cube of this many bins
#: across a face (about 5.6 deg)
SURROUND_BINS = 16


def _check(points: torch.Tensor) -> None:
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points must be (N, 3), got {tuple(points.shape)}")


class Spread(NamedTuple):
    """Where a cloud is and how big: its coordinate-wise median ``centre (3,)`` float64 and
    the median distance of its points from it (``radius``)."""

    centre: np.ndarray
    radius: float


def spread(points: np.ndarray | torch.Tensor) -> Spread:
    """The :class:`Spread` of ``points (N, 3)`` (zeros and radius 0.0 for fewer than 2
    points; radius inf where the distances overflow). O(N): medians by selection, no sort."""
    _check(points)
    pts = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else points
    pts = np.asarray(pts, dtype=np.float64)
    if len(pts) < 2:
        return Spread(np.zeros(3), 0.0)
    columns = [pts[:, k] for k in range(3)]  # numpy reduces (N, 3) along axis 0 slowly
    centre = np.array([np.median(c) for c in columns])
    return Spread(centre, float(np.median(_distances(columns, centre))))


def _distances(columns: list[np.ndarray], centre: np.ndarray) -> np.ndarray:
    """``(N,)`` Euclidean distances of the points whose coordinates are ``columns`` (3 of
    ``(N,)``) from ``centre (3,)``, inf where they overflow."""
    with np.errstate(over="ignore", invalid="ignore"):
        squared = np.square(columns[0] - centre[0])
        for k in (1, 2):
            squared += np.square(columns[k] - centre[k])
        return np.sqrt(squared, out=squared)


def even_radius(points: np.ndarray | torch.Tensor) -> float:
    """The radius (:func:`cloud_radius`) of ``points (N, 3)`` thinned to one point per cube of
    :data:`EVEN_CELL` of their radius: the size of the scene rather than of where the points
    crowd. A laser scanner's points crowd around it (the density falls with the square of the
    range), so the simulated rooms of 5 to 9 m of docs/rooms.md have radii of 1.1 to 2.6 m
    and, thinned evenly, 2.0 to 3.5 m; a fused fragment reads about the same both ways. 0.0
    for fewer than 2 points or no extent."""
    _check(points)
    pts = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else points
    pts = np.asarray(pts, dtype=np.float64)
    centre, radius = spread(pts)
    if len(pts) < 2 or not 0.0 < radius < math.inf:
        return 0.0
    pts = pts[:: max(1, math.ceil(len(pts) / EVEN_SAMPLES))]
    offset = pts - centre
    with np.errstate(over="ignore", invalid="ignore"):
        near = np.abs(offset).max(axis=1) <= EVEN_REACH * radius
    cells = np.floor(offset[near] / (EVEN_CELL * radius)).astype(np.int64)
    # within EVEN_REACH radii: at most 2 * 30 * 30 = 1800 cells each way, 12 bits a coordinate
    keys = (cells[:, 0] + 2048) << 24 | (cells[:, 1] + 2048) << 12 | (cells[:, 2] + 2048)
    return cloud_radius(offset[near][first_of_keys(keys)])


def surround_share(points: np.ndarray | torch.Tensor) -> float:
    """The share of the directions around the origin (bins of about 5.6 deg on a cube) in
    which ``points (N, 3)`` lie: a terrestrial laser scanner's panorama in its own frame 0.85
    to 0.97 (the simulated rooms), a spinning LiDAR's 0.3, a depth frame's field of view
    0.05, a cloud far from its origin less (0.0 for no point)."""
    _check(points)
    pts = points if isinstance(points, torch.Tensor) else torch.from_numpy(np.asarray(points))
    pts = pts[:: max(1, math.ceil(len(pts) / EVEN_SAMPLES))].to(torch.float64)
    if not len(pts):
        return 0.0
    index, _ = cube_bins(pts, SURROUND_BINS)
    return len(torch.unique(index)) / (6 * SURROUND_BINS * SURROUND_BINS)


def cloud_radius(points: np.ndarray | torch.Tensor) -> float:
    """Median distance of ``points (N, 3)`` from their coordinate-wise median (0.0 for fewer
    than 2 points): the size of a scan, robust to a few stray points far away
    (:func:`spread`'s radius)."""
    return spread(points).radius


def nearest_spacing(
    points: torch.Tensor,
    generator: torch.Generator | None = None,
    samples: int = SPACING_SAMPLES,
) -> float:
    """Median nearest-neighbour distance of ``points (N, 3)``: the sampling step of a scan
    (the median of :func:`nearest_distances`; 0.0 when the cloud has fewer than 2 distinct
    points)."""
    dist = nearest_distances(points, generator, samples)
    return float(np.median(dist)) if len(dist) else 0.0


def spacing_spread(distances: np.ndarray) -> float:
    """How unevenly a cloud is sampled, from its :func:`nearest_distances`: their 90th
    percentile over their 10th. A scanner at a near constant range samples evenly (simulated
    laser scans of objects 1.3 to 2.1, a fused tabletop box 1.6 to 1.8); one within the scene,
    whose step grows with the range, does not (LiDAR streets 4.5 to 9.1, terrestrial scans
    of rooms 5.8 to 6.6). nan for no distances."""
    if not len(distances):
        return float("nan")
    low, high = np.percentile(distances, [10.0, 90.0])
    return float(high / low) if low > 0 else float("inf")


def nearest_distances(
    points: torch.Tensor,
    generator: torch.Generator | None = None,
    samples: int = SPACING_SAMPLES,
) -> np.ndarray:
    """Nearest-neighbour distances ``(S,)`` of a seeded random subset of ``samples`` points of
    ``points (N, 3)``, each to the nearest other distinct point.

    Measured against the whole cloud with a k-d tree (``pykdtree``; ``benchmarks/kdtree.py``
    measures it against SciPy's and Open3D's): O(N log N) time and O(N) memory however
    unevenly the points are spread (a spinning LiDAR puts thousands of returns near its
    sensor and a few far away). Duplicate points (distance 0) are left out: a query with
    :data:`SPACING_NEIGHBOURS` or more copies of itself is asked again among the distinct
    points. Empty when the cloud has fewer than 2 distinct points.

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
        return np.zeros(0)
    generator = generator or torch.Generator().manual_seed(0)
    asked = pts[torch.randperm(n, generator=generator)[: min(samples, n)].numpy()]
    dist, _ = KDTree(pts, leafsize=KDTREE_LEAF).query(asked, k=min(SPACING_NEIGHBOURS, n))
    dist = np.where(dist > 0, dist, np.inf).min(axis=1)
    stuck = ~np.isfinite(dist)
    if stuck.any():
        distinct = np.unique(pts, axis=0)
        if len(distinct) < 2:
            return np.zeros(0)
        dist[stuck] = KDTree(distinct).query(asked[stuck], k=2)[0][:, 1]
    return dist


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

    def centroid(self, points: np.ndarray) -> np.ndarray:
        """``(3,)`` float64 mean of the inside points of ``points (N, 3)``, in the input's
        coordinates: where the cloud is, whatever strays lie far away."""
        return (points if self.inside is None else points[self.inside]).mean(axis=0)

    def local(self, points: np.ndarray) -> np.ndarray:
        """``(K, 3)`` float64 local coordinates of the inside points of ``points (N, 3)``
        (the array itself when nothing moves and nothing is left out). The median point is
        a point of the cloud's box: near points subtract without rounding (Sterbenz)."""
        kept = points if self.inside is None else points[self.inside]
        return kept - self.origin if self.moved else kept


def far_from_origin(centre: np.ndarray, radius: float) -> bool:
    """Whether a cloud of median point ``centre (3,)`` and ``radius`` lies more than
    :data:`FAR_RADII` radii from the origin (a georeferenced scan: its origin is not its
    sensor's)."""
    return bool(np.abs(centre).max() > FAR_RADII * radius)


def local_frame(points: np.ndarray, measured: Spread | None = None) -> LocalFrame:
    """The :class:`LocalFrame` of ``points (N, 3)`` float64 (finite); ``measured``: their
    :func:`spread`, when it is known. O(N)."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points must be (N, 3), got {tuple(points.shape)}")
    zero = np.zeros(3)
    if len(points) < 2:
        return LocalFrame(zero, None, 0.0)
    centre, radius = spread(points) if measured is None else measured
    if not radius > 0 or not np.isfinite(radius):
        return LocalFrame(zero, None, radius)
    origin = centre if far_from_origin(centre, radius) else zero
    reach = STRAY_RADII * radius
    columns = [points[:, k] for k in range(3)]
    with np.errstate(over="ignore", invalid="ignore"):
        corner = [
            max(abs(c.min() - m), abs(c.max() - m)) for c, m in zip(columns, centre, strict=True)
        ]
        if math.sqrt(sum(x * x for x in corner)) <= reach:  # the box's farthest corner is
            return LocalFrame(origin, None, radius)  # within reach: no point is a stray
    inside = _distances(columns, centre) <= reach
    return LocalFrame(origin, None if inside.all() else inside, radius)


def _first_per_voxel(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Increasing indices of the first point of ``points (N, 3)`` in each occupied voxel: the
    points :func:`~byoc_cli.geometry.voxel.voxelize` keeps (the measure runs it once per step
    of a ladder)."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(points / voxel_size).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) < 2.0**62:  # one int64 key per cell
        return first_of_keys((cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2])
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


def first_of_keys(keys: np.ndarray) -> np.ndarray:
    """Increasing indices of the first occurrence of each distinct value of ``keys (N,)``
    (int64): ``np.sort(np.unique(keys, return_index=True)[1])``, from torch's stable sort,
    about 5 times faster on the CPU than numpy's (1M keys: 15 ms against 80 ms)."""
    if len(keys) == 0:
        return np.zeros(0, dtype=np.int64)
    ordered, order = torch.sort(torch.from_numpy(np.ascontiguousarray(keys)), stable=True)
    starts = torch.ones(len(keys), dtype=torch.bool)
    starts[1:] = ordered[1:] != ordered[:-1]
    first = torch.zeros(len(keys), dtype=torch.bool)
    first[order[starts]] = True
    return np.flatnonzero(first.numpy())


def linear_share(
    points: torch.Tensor,
    voxel_size: float,
    generator: torch.Generator | None = None,
    samples: int = SPACING_SAMPLES,
) -> float:
    """Share of the kept points of ``points (N, 3)`` at ``voxel_size`` whose neighbourhood is
    a line: what a voxel grid shows of a scan sampled along lines.

    The kept points are the first point per voxel (those of
    :func:`byoc_cli.geometry.voxel.voxelize`, what the feature extractors see). For a seeded
    random subset of ``samples`` of them, the neighbourhood is the kept points within
    :data:`LINE_RADIUS` voxels (the :data:`LINE_NEIGHBOURS` nearest, k-d tree); its
    principal standard deviations
    ``s1 >= s2 >= s3`` give its linearity ``(s1 - s2) / s1``, and it is a line above
    :data:`LINEARITY`. Neighbourhoods of fewer than :data:`LINE_MIN_POINTS` points (isolated
    points) are left out. Scan lines further apart than about ``LINE_RADIUS`` voxels make most
    neighbourhoods lines (a spinning LiDAR's rings at the sampling step: 34 % to 99 % of them);
    a surface sampled evenly at the voxel makes almost none (depth-camera frames and 3DMatch
    fragments: at most 5 %).

    Args:
        points: ``(N, 3)``, finite.
        voxel_size: the voxel, in the units of the points (> 0).
        generator: draws the query subset (default: seed 0).
        samples: query points at most.

    Returns:
        The share in [0, 1]; 0.0 when no query has a neighbourhood of
        :data:`LINE_MIN_POINTS` points.

    Raises:
        ShapeError: ``points`` is not ``(N, 3)`` or ``voxel_size`` is not positive.
    """
    sd = _checked_spreads(points, voxel_size, LINE_NEIGHBOURS, LINE_RADIUS, generator, samples)
    if sd is None:
        return 0.0
    linearity = (sd[:, 2] - sd[:, 1]) / np.maximum(sd[:, 2], np.finfo(np.float64).tiny)
    return float((linearity > LINEARITY).mean())


def rough_share(
    points: torch.Tensor,
    voxel_size: float,
    generator: torch.Generator | None = None,
    samples: int = ROUGH_SAMPLES,
) -> float:
    """Share of the kept points of ``points (N, 3)`` at ``voxel_size`` whose neighbourhood is
    not a smooth surface: edges, corners, clutter, noise.

    The kept points are those of :func:`linear_share`; for a seeded random subset of
    ``samples`` of them, the neighbourhood is the :data:`ROUGH_NEIGHBOURS` nearest kept points
    (within :data:`ROUGH_RADIUS` voxels; a surface sampled at the voxel puts them within about
    4.5), and its surface variation ``s3^2 / (s1^2 + s2^2 + s3^2)`` (``s1 >= s2 >= s3``: the
    standard deviations along its principal axes; 0 on a plane, 1/3 for points spread alike
    in every direction) is rough above :data:`ROUGHNESS`. Rooms, desks, 3DMatch fragments,
    LiDAR streets and scans of boxes have edges and clutter: 25 % to 94 % of their
    neighbourhoods are rough at the auto voxel; laser scans of smooth free-form objects at
    most 6 % (``benchmarks/objects.py cues``).

    Args:
        points: ``(N, 3)``, finite.
        voxel_size: the voxel, in the units of the points (> 0).
        generator: draws the query subset (default: seed 0).
        samples: query points at most.

    Returns:
        The share in [0, 1]; 0.0 when no query has a neighbourhood of
        :data:`LINE_MIN_POINTS` points.

    Raises:
        ShapeError: ``points`` is not ``(N, 3)`` or ``voxel_size`` is not positive.
    """
    sd = _checked_spreads(points, voxel_size, ROUGH_NEIGHBOURS, ROUGH_RADIUS, generator, samples)
    if sd is None:
        return 0.0
    var = sd**2
    variation = var[:, 0] / np.maximum(var.sum(axis=1), np.finfo(np.float64).tiny)
    return float((variation > ROUGHNESS).mean())


def _checked_spreads(points, voxel_size, neighbours, radius, generator, samples):
    """:func:`_neighbourhood_spreads` of ``points (N, 3)`` (at least :data:`LINE_MIN_POINTS`
    a neighbourhood) once they and ``voxel_size`` are checked.

    Raises:
        ShapeError: ``points`` is not ``(N, 3)`` or ``voxel_size`` is not positive.
    """
    _check(points)
    if not voxel_size > 0:
        raise ShapeError(f"voxel_size must be > 0, got {voxel_size}")
    return _neighbourhood_spreads(
        points, voxel_size, neighbours, radius, LINE_MIN_POINTS, generator, samples
    )


def _neighbourhood_spreads(
    points: torch.Tensor,
    voxel_size: float,
    neighbours: int,
    radius: float,
    min_points: int,
    generator: torch.Generator | None,
    samples: int,
) -> np.ndarray | None:
    """``(S, 3)`` the principal standard deviations (ascending: ``s3, s2, s1``) of the
    neighbourhoods of a seeded random subset of ``samples`` kept points of ``points (N, 3)``
    at ``voxel_size`` (the first point per voxel): the ``neighbours`` nearest kept points
    within ``radius`` voxels (k-d tree), neighbourhoods of fewer than ``min_points`` left out;
    None when none is left."""
    from pykdtree.kdtree import KDTree

    pts = np.ascontiguousarray(points.detach().cpu().numpy(), dtype=np.float64)
    pts = pts[_first_per_voxel(pts, voxel_size)]
    n = len(pts)
    if n < min_points:
        return None
    generator = generator or torch.Generator().manual_seed(0)
    asked = pts[torch.randperm(n, generator=generator)[: min(samples, n)].numpy()]
    k = min(neighbours, n)
    dist, idx = KDTree(pts).query(asked, k=k, distance_upper_bound=radius * voxel_size)
    found = np.isfinite(dist.reshape(len(asked), k))  # (S, k); missing neighbours: inf
    count = found.sum(axis=1)
    shaped = count >= min_points
    if not shaped.any():
        return None
    weight = found[shaped].astype(np.float64)[..., None]  # (S', k, 1)
    near = pts[np.where(found, idx.reshape(len(asked), k), 0)[shaped]]  # (S', k, 3)
    mean = (near * weight).sum(axis=1) / count[shaped, None]
    centred = (near - mean[:, None]) * weight
    cov = np.einsum("ski,skj->sij", centred, centred) / count[shaped, None, None]
    return np.sqrt(np.clip(np.linalg.eigvalsh(cov), 0.0, None))
