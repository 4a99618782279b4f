"""``--voxel-size auto``: the feature voxel of a pair, read from how the clouds are sampled.

Features work at the scale they were made for: the learned encoder at the voxel it was trained
at (2.5 cm on depth frames of rooms and desks, whose radius, the median distance of the points
from their median, lies between :data:`TRAINED_RADIUS` ``[0]`` and ``[1]``), FPFH at its
tutorial voxel (5 cm) on scans of the same size. Choosing the voxel is choosing a scale: a
voxel ``k`` times larger runs the same computation as coordinates ``k`` times smaller, and
refinement levels, inlier thresholds and overlap radii are all multiples of the voxel.

The rule (:func:`choose_voxel`), on the two clouds of a pair together:

1. **Size.** ``r``, the larger of the two radii. Inside the trained range the reference voxel
   is kept as it is; outside it the voxel scales with the data, ``reference * r /``
   :data:`CENTRE_RADIUS` (millimetres, an object a few centimetres across, a LiDAR scan tens
   of metres wide: all brought to the middle of the trained range).
2. **Density.** At least :data:`DENSITY_FACTOR` times the nearest-neighbour spacing of the
   sparser cloud. When one cloud is sampled more sparsely than the other (spacings more than
   :data:`MISMATCH_RATIO` apart), the features of the denser one are computed from a random
   share of its points (:attr:`VoxelChoice.keep`) that gives it the sparser one's spacing: the
   features of a cloud with holes at the voxel (thinned after voxelisation) do not match those
   of a cloud without, and two clouds thinned alike do match.
3. **Scan lines.** A scan sampled along lines (a spinning LiDAR's rings, a line scanner's
   scan lines) is dense along them and sparse across: its nearest-neighbour spacing is the
   step along a line, and at a voxel smaller than the gap between the lines the features see
   the lines, which are fixed to the sensor and the same in every scan (rings on the ground
   match themselves and the pair registers to the identity). :func:`measure` tells such a
   cloud by its neighbourhoods at the density voxel (``DENSITY_FACTOR`` spacings): more than
   :data:`SCAN_LINE_SHARE` of them are lines (:func:`~byoc_cli.geometry.sampling.linear_share`;
   LiDAR 34 % to 99 %, depth frames and 3DMatch fragments at most 5 %). The voxel of such a
   cloud is at least the smallest one, growing by :data:`LINE_STEP`, at which at most
   :data:`LINE_FREE_SHARE` of the neighbourhoods are lines (:attr:`CloudScale.line_voxel`; at
   most :data:`MAX_LINE_VOXEL` of its radius): the lines are washed out into surfaces.

The refinement does not coarsen with the density floor or the scan lines: it runs on the
full-resolution clouds at the voxel of step 1 (:attr:`VoxelChoice.refine_voxel`), so a voxel
raised for the features does not cost the final accuracy. An explicit voxel size bypasses all
of this.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.errors import RegistrationError
from byoc_cli.geometry.sampling import (
    Spread,
    even_radius,
    far_from_origin,
    linear_share,
    nearest_distances,
    spacing_spread,
    spread,
    surround_share,
)

#: radii (metres, median distance from the median point) of the depth frames and fragments
#: the reference voxels are measured on: tabletop frames 0.15 m to a room's 1.5 m
TRAINED_RADIUS = (0.15, 1.6)
#: where data of another size are brought (geometric middle of the trained range)
CENTRE_RADIUS = 1.0
#: the voxel is at least this many nearest-neighbour spacings of the sparser cloud
DENSITY_FACTOR = 1.8
#: clouds whose spacings differ by more than this are thinned alike for their features
MISMATCH_RATIO = 1.25
#: the smallest share of a cloud's points its features are computed from
MIN_KEEP = 0.02
#: fewest distinct points a cloud needs for its scale to be read from it
MIN_POINTS = 32
#: clouds of one pair whose radii differ more than this are taken for different units
MAX_RADIUS_RATIO = 30.0
#: a cloud whose :attr:`CloudScale.dimension` exceeds this fills a volume: not a scan
MAX_DIMENSION = 2.8
#: a cloud is sampled along lines when more than this share of its kept points at the density
#: voxel (``DENSITY_FACTOR`` spacings) have linear neighbourhoods
SCAN_LINE_SHARE = 0.2
#: its lines are washed out at a voxel where at most this share are (the rest: poles, edges,
#: far sparse returns; simulated street scans at 16 to 64 rings level out at 3 % to 4 %)
LINE_FREE_SHARE = 0.05
#: the factor by which the voxel grows from the density voxel until then
LINE_STEP = 2.0**0.5
#: ... up to this share of the cloud's radius at most
MAX_LINE_VOXEL = 0.15
#: a cloud whose points lie in at least this share of the directions around its origin is a
#: panorama (a terrestrial laser scan in its scanner's frame: 0.85 to 0.97 on the simulated
#: rooms; LiDAR streets 0.32, fragments at most 0.14, depth frames 0.05), whose
#: :attr:`CloudScale.even_radius` is measured; a georeferenced cloud is read about its median
#: point (the rooms 0.89 to 0.99, the streets 0.25, 3DMatch fragments 0.25 to 0.58)
PANORAMA = 0.5


class CloudScale(NamedTuple):
    """How one cloud is sampled, in its own units.

    Attributes:
        num_points: points of the cloud.
        spacing: median nearest-neighbour distance (0 when fewer than 2 distinct points).
        radius: median distance of the points from their coordinate-wise median.
        label: how messages name the cloud.
        line_voxel: for a cloud sampled along lines, the smallest voxel at which they wash
            out (:func:`scan_line_voxel`); 0.0 for a cloud sampled evenly; None when not
            measured (the registration from an initial pose needs no feature voxel).
        even_radius: for a panorama (:data:`PANORAMA`), the radius of the cloud thinned
            evenly (:func:`~byoc_cli.geometry.sampling.even_radius`): larger than ``radius``
            where the points crowd around the scanner; FPFH's size (:func:`size_radius`).
            None: not a panorama, or not measured.
        origin_radii: how far the median point lies from the origin, in radii: where the
            sensor that saw the cloud stood, when the cloud is in its frame (None: not
            measured). Depth frames and 3DMatch fragments 1.7 to 2.8, scans of a panorama
            or a street below 1, laser scans of an object from outside it 3 to 11.
        spacing_spread: how unevenly the cloud is sampled
            (:func:`~byoc_cli.geometry.sampling.spacing_spread`: the 90th percentile of the
            nearest-neighbour distances over the 10th; None: not measured).
    """

    num_points: int
    spacing: float
    radius: float
    label: str = "cloud"
    line_voxel: float | None = 0.0
    even_radius: float | None = None
    origin_radii: float | None = None
    spacing_spread: float | None = None

    @property
    def dimension(self) -> float:
        """How the point count grows with size, ``log N / log(radius / spacing)``: about 2
        for a scanned surface (2.1 to 2.5 for depth frames and fragments), 3 for points that
        fill a volume (noise); nan without extent."""
        if self.spacing <= 0 or self.radius <= self.spacing or self.num_points < 2:
            return float("nan")
        return math.log(self.num_points) / math.log(self.radius / self.spacing)


class VoxelChoice(NamedTuple):
    """The voxel of a pair and why.

    Attributes:
        voxel_size: in the units of the points.
        refine_voxel: the voxel of the refinement levels (step 1's, before the density floor).
        reference: the features' own voxel (trained, or FPFH's default), in metres.
        factor: ``voxel_size / reference``: the scale the data were brought to.
        reason: one sentence for reports and logs.
        scales: the :class:`CloudScale` of each cloud the choice read.
        keep: per cloud, the share of its points its features are computed from (1.0: all;
            below 1 for a cloud denser than the other, so that both are sampled alike).
    """

    voxel_size: float
    refine_voxel: float
    reference: float
    factor: float
    reason: str
    scales: tuple[CloudScale, ...]
    keep: tuple[float, ...] = ()

    @property
    def scan_lines(self) -> bool:
        """Whether a cloud of the pair is sampled along lines (:attr:`CloudScale.line_voxel`)."""
        return any((s.line_voxel or 0.0) > 0 for s in self.scales)

    def keep_of(self, index: int) -> float:
        """The share of cloud ``index``'s points its features are computed from."""
        return self.keep[index] if index < len(self.keep) else 1.0

    def as_dict(self) -> dict:
        """JSON-ready: voxel, reference, factor, reason and each cloud's spacing and radius."""
        return {
            "voxel_size": self.voxel_size,
            "refine_voxel_size": self.refine_voxel,
            "reference_voxel_size": self.reference,
            "factor": self.factor,
            "reason": self.reason,
            "clouds": [s._asdict() for s in self.scales],
            "feature_points_kept": list(self.keep),
        }


def measure(
    points: torch.Tensor, label: str = "cloud", lines: bool = True, measured: Spread | None = None
) -> CloudScale:
    """The :class:`CloudScale` of ``points (N, 3)`` (``lines`` False: without
    :attr:`~CloudScale.line_voxel`, None; :func:`scan_line_voxel` is most of the cost;
    ``measured``: their :func:`~byoc_cli.geometry.sampling.spread` when it is known).

    Raises:
        RegistrationError: fewer than :data:`MIN_POINTS` distinct points (no scale can be
            read from them), or points spread too wide for any unit
            (:func:`check_radius`); the message starts with ``label``.
    """
    distinct = len(torch.unique(points, dim=0)) if len(points) < 10 * MIN_POINTS else len(points)
    if distinct < MIN_POINTS:
        raise RegistrationError(_too_few(points, distinct, label))
    centre, radius = spread(points) if measured is None else measured
    check_radius(radius, label)
    distances = nearest_distances(points)
    spacing = float(np.median(distances)) if len(distances) else 0.0
    if radius <= 0 or spacing <= 0 or radius < 2 * spacing:  # no extent: a few points repeated?
        distinct = len(np.unique(points.numpy(), axis=0))
        if distinct < MIN_POINTS:
            raise RegistrationError(_too_few(points, distinct, label))
    line_voxel = scan_line_voxel(points, spacing, radius) if lines else None
    around = points - torch.from_numpy(centre) if far_from_origin(centre, radius) else points
    even = even_radius(points) if surround_share(around) >= PANORAMA else None
    origin = float(np.linalg.norm(centre)) / radius if radius > 0 else None
    uneven = spacing_spread(distances) if len(distances) else None
    return CloudScale(len(points), spacing, radius, label, line_voxel, even, origin, uneven)


#: float32 coordinates this far from the origin lie 1 cm or more apart
FLOAT32_FAR = 1e5


def _too_few(points: torch.Tensor, distinct: int, label: str) -> str:
    """The message for a cloud of ``distinct`` distinct points, naming float32 rounding
    where the coordinates lie far enough from the origin for it to merge points."""
    why = ""
    offset = float(points.abs().max()) if len(points) else 0.0
    pts = points.to(torch.float64)
    single = offset < 3e38 and bool((pts.to(torch.float32).to(torch.float64) == pts).all())
    if len(points) > distinct and single and offset >= FLOAT32_FAR:
        step = float(np.spacing(np.float32(offset)))
        why = (
            f" (its coordinates reach {offset:.3g}, where float32 values lie {step:.3g} apart: "
            "store them as double, or about a local origin)"
        )
    return (
        f"{label}: only {distinct} distinct point(s){why}; at least {MIN_POINTS} are needed to "
        "read the scan's scale (or give --voxel-size)"
    )


#: the largest radius (median distance from the median point) of a cloud in any unit: a
#: 100 m scan in nanometres has 1e11; past about 1e19 float32 squares overflow
MAX_RADIUS = 1e12


def check_radius(radius: float, label: str) -> None:
    """Refuse a cloud whose ``radius`` exceeds :data:`MAX_RADIUS` (or is not finite).

    Raises:
        RegistrationError: naming ``label`` and the radius.
    """
    if not radius <= MAX_RADIUS:
        raise RegistrationError(
            f"{label}: the points spread {radius:.3g} units from their median point, more than "
            f"{MAX_RADIUS:g} (no scan is that large in any unit): is the file's scale right? "
            "(--scale multiplies the coordinates)"
        )


def scan_line_voxel(points: torch.Tensor, spacing: float, radius: float) -> float:
    """For ``points (N, 3)`` sampled along lines, the smallest voxel that washes them out;
    0.0 for points sampled evenly (the module docstring's step 3).

    Args:
        points: ``(N, 3)``.
        spacing, radius: the cloud's :attr:`CloudScale.spacing` and :attr:`CloudScale.radius`.

    Returns:
        0.0 when at most :data:`SCAN_LINE_SHARE` of the kept points at ``DENSITY_FACTOR *
        spacing`` have linear neighbourhoods
        (:func:`~byoc_cli.geometry.sampling.linear_share`); otherwise the first voxel of
        ``DENSITY_FACTOR * spacing * LINE_STEP ** k`` (``k = 1, 2, ...``) at which at most
        :data:`LINE_FREE_SHARE` have, or ``MAX_LINE_VOXEL * radius`` when that comes first.
    """
    voxel = DENSITY_FACTOR * spacing
    if spacing <= 0 or radius <= 0 or linear_share(points, voxel) <= SCAN_LINE_SHARE:
        return 0.0
    largest = MAX_LINE_VOXEL * radius
    while True:
        voxel *= LINE_STEP
        if voxel >= largest:
            return largest
        if linear_share(points, voxel) <= LINE_FREE_SHARE:
            return voxel


def choose_voxel(
    scales: tuple[CloudScale, ...], reference: float, even: bool = False
) -> VoxelChoice:
    """The voxel of a pair (or of one cloud) from the clouds' :class:`CloudScale` (see the
    module docstring for the rule).

    Args:
        scales: one per cloud (both clouds of a pair: they must share one voxel).
        reference: the features' own voxel in metres.
        even: size the clouds by their :attr:`~CloudScale.even_radius` where it is above
            the trained range (FPFH: :func:`size_radius`).

    Raises:
        RegistrationError: a cloud has no size (all points within one spacing of each other).
    """
    radius = max(s.radius for s in scales)
    spacing = max(s.spacing for s in scales)
    alike = spacing <= MISMATCH_RATIO * min(s.spacing for s in scales)
    if radius <= 0 or spacing <= 0 or radius < 2 * spacing:
        raise RegistrationError(
            f"the clouds have no extent to register (radius {radius:.3g}, point spacing "
            f"{spacing:.3g}); give --voxel-size if this is intended"
        )
    for scale in scales:
        if scale.dimension > MAX_DIMENSION:
            raise RegistrationError(
                f"{scale.label}: the points fill a volume (dimension {scale.dimension:.2f}; a "
                "scanned surface is about 2): noise, not a scan? Give --voxel-size to register "
                "it as it is"
            )
    small = min(scales, key=lambda s: s.radius)
    large = max(scales, key=lambda s: s.radius)
    if small.radius > 0 and large.radius / small.radius > MAX_RADIUS_RATIO:
        raise RegistrationError(
            f"{large.label}: {large.radius / small.radius:.0f} times the size of "
            f"{small.label} (radius {large.radius:.3g} against {small.radius:.3g}): are they "
            "in the same units? Give each one's factor to metres (--source-scale, "
            "--target-scale), or --voxel-size to register them as they are"
        )
    low, high = TRAINED_RADIUS
    if low <= radius <= high:
        voxel, why = reference, f"radius {radius:.3g} is in the trained range"
    else:
        voxel = reference * radius / CENTRE_RADIUS
        side = "below" if radius < low else "above"
        why = f"radius {radius:.3g} is {side} the trained range {low:g}-{high:g}; scaled"
    refine_voxel = voxel
    size = size_radius(scales) if even else radius
    if size != radius:  # the features see the scene; the refinement keeps step 1's voxel
        voxel = reference * size / CENTRE_RADIUS
        why += f"; features at {size:.3g}, the radius thinned evenly (points crowd near a scanner)"
    if DENSITY_FACTOR * spacing > voxel:
        voxel = DENSITY_FACTOR * spacing
        why += (
            f"; raised to {DENSITY_FACTOR:g} x the point spacing {spacing:.3g} of the sparser cloud"
        )
    lines = max(s.line_voxel or 0.0 for s in scales)
    if any(s.line_voxel is None for s in scales):
        why += "; scan lines not measured (no features)"
    elif lines > voxel:
        voxel = lines
        why += f"; raised to {lines:.3g}, where the scan lines of the clouds wash out"
    keep = tuple(
        1.0 if alike or s.spacing <= 0 else max(MIN_KEEP, min(1.0, (s.spacing / spacing) ** 2))
        for s in scales
    )
    if not alike:
        why += "; the denser cloud's features from a share of its points, as sparse as the other"
    return VoxelChoice(voxel, refine_voxel, reference, voxel / reference, why, tuple(scales), keep)


#: radii, in the clouds' units, of an object 1 to 15 cm in radius measured in millimetres (the
#: trained range starts at 0.15 m): by size alone a scene 10 to 150 m in radius in metres
MILLIMETRE_OBJECT = (10.0, 1000.0 * TRAINED_RADIUS[0])
#: a cloud whose median point lies at least this many radii from its origin was seen from
#: outside it (:attr:`CloudScale.origin_radii`: simulated laser scans of objects 8.6 to 10.5,
#: a fused tabletop object 3.1 to 3.3; depth frames and 3DMatch fragments at most 2.8, cut
#: pieces of fragments 3.9); FAR_RADII and beyond: georeferenced, no sensor at the origin
SEEN_FROM_OUTSIDE = 4.0
#: a scan of an object, taken from outside it at a near constant range, is sampled evenly:
#: its :attr:`CloudScale.spacing_spread` is at most this (simulated laser scans of objects
#: 1.3 to 2.1, a fused tabletop box 1.6 to 1.8); a LiDAR street or a terrestrial laser scan,
#: whose step grows with the range from a sensor within it, is not (streets 4.5 to 9.1, rooms
#: 5.8 to 6.6)
EVEN_SAMPLING = 3.0


def object_in_millimetres(scales: tuple[CloudScale, ...]) -> bool:
    """Whether clouds of ``scales`` read as a laser scan of an object in millimetres: each one
    sized as a 1 to 15 cm object in millimetres (:data:`MILLIMETRE_OBJECT`), seen from outside
    it by a sensor at its origin (:data:`SEEN_FROM_OUTSIDE` up to FAR_RADII radii away),
    sampled evenly (:data:`EVEN_SAMPLING`), not along lines, and not a panorama. A LiDAR scan
    of a street of that size (rings, a step that grows with the range, its sensor within it
    unless moved into a map's frame), a terrestrial laser scan (a panorama) and a
    georeferenced cloud are not; a depth frame or a 3DMatch fragment is smaller in any unit
    but centimetres, and seen from within 2.8 radii."""
    from byoc_cli.geometry.sampling import FAR_RADII

    low, high = MILLIMETRE_OBJECT
    return bool(scales) and all(
        low <= s.radius < high
        and s.even_radius is None
        and not s.line_voxel
        and s.origin_radii is not None
        and SEEN_FROM_OUTSIDE <= s.origin_radii < FAR_RADII
        and s.spacing_spread is not None
        and s.spacing_spread <= EVEN_SAMPLING
        for s in scales
    )


def size_radius(scales: tuple[CloudScale, ...]) -> float:
    """The size by which FPFH's voxel scales: the larger radius of ``scales``, or their larger
    :attr:`~CloudScale.even_radius` where that is above the trained range. FPFH describes
    the geometry within :data:`~byoc_cli.pipeline.features.FPFH_FEATURE_RADIUS` voxels of a
    point: on a laser-scanned room, whose points crowd around the scanner, the raw radius
    keeps its 5 cm tutorial voxel, at which Open3D's FPFH + RANSAC registers none of the 14
    simulated rooms of docs/rooms.md (8 at 0.1 m and at 0.2 m). Clouds that are not panoramas
    (depth frames, whose far background is sparse: at FPFH's coarser voxel two Kinect frame
    pairs of a cabinet passed 17 and 32 cm off), clouds sized inside the trained range by
    both measures and clouds scaled down (objects) keep their radius."""
    radius = max(s.radius for s in scales)
    wide = max((s.even_radius or 0.0) for s in scales)
    return wide if wide > max(radius, TRAINED_RADIUS[1]) else radius


def trained_scale(choice: VoxelChoice) -> float | None:
    """The factor that brings clouds of ``choice`` to the size the features were made for
    (their refinement voxel becomes the reference voxel); None when they are that size
    already. Commands whose every setting is in metres of the trained scale
    (``register-scans``) multiply the coordinates by it and divide the results' translations
    by it."""
    if choice.refine_voxel == choice.reference:
        return None
    return choice.reference / choice.refine_voxel
