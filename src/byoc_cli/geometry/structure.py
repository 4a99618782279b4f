"""A cloud's structure (the few large planes along its main surface directions: a room's floor,
ceiling and walls) and the fit of what is not structure under a transform.

A room turned 90 or 180 deg onto itself about its up axis fits its floor, ceiling and walls
as well as the truth does; what stands in the room (tables, shelves, boxes) does not. So the
share of a source's non-structure points that land next to the target under ``T``
(:func:`clutter_fit`) tells such a turn from the truth where the overall fit cannot.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.orientation import main_directions, point_normals, thinnest
from byoc_cli.geometry.voxel import voxelize

#: a point lies along a main direction when its normal is within this of it (either sign)
STRUCTURE_CONE_DEG = 15.0
#: a plane is structure when its slab (STRUCTURE_SLAB voxels thick) holds this share of the
#: points at least
STRUCTURE_MIN_SHARE, STRUCTURE_SLAB = 0.04, 2.0
#: normals sampled for the main directions
STRUCTURE_SAMPLES = 2000
#: the cells of a turn's :func:`correlation_shift`, in voxels; the percentiles of the points
#: its grids span, and the cells of a grid at most (coarser cells beyond)
CORRELATION_CELL = 3.0
CORRELATION_SPAN = (1.0, 99.0)
CORRELATION_CELLS = 2**16


class Structure(NamedTuple):
    """Result of :func:`structure`.

    Attributes:
        points: ``(S, 3)`` float64 the cloud's voxel representatives (first point per voxel).
        mask: ``(S,)`` bool, True on a large plane along a main direction.
        directions: ``(D, 3)`` the main directions, strongest first.
        normals: ``(S, 3)`` the representatives' unit normals (either sign).
        up: index into ``directions`` of the one the points spread least along.
    """

    points: np.ndarray
    mask: np.ndarray
    directions: np.ndarray
    normals: np.ndarray
    up: int


def structure(
    points: np.ndarray, voxel_size: float, generator: torch.Generator | None = None
) -> Structure:
    """The large planes of ``points (N, 3)`` at ``voxel_size``: of the voxel representatives,
    those whose normal lies within :data:`STRUCTURE_CONE_DEG` of a main surface direction
    (:func:`byoc_cli.geometry.orientation.main_directions` on a seeded sample of normals) and
    whose offset along it falls in a slab of :data:`STRUCTURE_SLAB` voxels that holds at
    least :data:`STRUCTURE_MIN_SHARE` of all representatives (with its two neighbouring
    slabs: a plane that straddles a slab edge, or a noisy one).

    Raises:
        ShapeError: ``points`` is not ``(N, 3)`` with ``N >= 3``, or ``voxel_size <= 0``.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise ShapeError(f"points must be (N, 3) with N >= 3, got {tuple(pts.shape)}")
    if not voxel_size > 0:
        raise ShapeError(f"voxel_size must be > 0, got {voxel_size}")
    kept = pts[voxelize(torch.from_numpy(pts), voxel_size).point_index.numpy()]
    if len(kept) < 3:
        return Structure(
            kept, np.zeros(len(kept), dtype=bool), np.eye(3)[2:], np.eye(3)[[2] * len(kept)], 0
        )
    normals = point_normals(kept, kept)
    generator = generator or torch.Generator().manual_seed(0)
    sample = torch.randperm(len(kept), generator=generator)[:STRUCTURE_SAMPLES].numpy()
    directions = np.stack(main_directions(normals[sample]))
    cone = math.cos(math.radians(STRUCTURE_CONE_DEG))
    slab = STRUCTURE_SLAB * voxel_size
    mask = np.zeros(len(kept), dtype=bool)
    for d in directions:
        along = np.abs(normals @ d) > cone
        offset = kept @ d
        bins = np.floor(offset / slab).astype(np.int64)
        lo = bins.min()
        counts = np.bincount(bins[along] - lo, minlength=bins.max() - lo + 1)
        big = counts >= STRUCTURE_MIN_SHARE * len(kept)
        near = big.copy()  # and the slabs either side
        near[1:] |= big[:-1]
        near[:-1] |= big[1:]
        mask |= along & near[bins - lo]
    return Structure(kept, mask, directions, normals, thinnest(kept, directions))


class ClutterFit(NamedTuple):
    """Result of :func:`clutter_fit`: shares of source representatives within the radius of
    a target one under ``T``.

    Attributes:
        clutter: of the source's non-structure points, near any target point.
        clutter_to_clutter: of the same, near a target non-structure point.
        structure: of the source's structure points, near any target point.
        overall: of all source representatives, near any target point.
        clutter_share: the share of the source's representatives that are not structure.
    """

    clutter: float
    clutter_to_clutter: float
    structure: float
    overall: float
    clutter_share: float


def clutter_fit(src: Structure, tgt: Structure, T: np.ndarray, radius: float) -> ClutterFit:
    """The fit of ``src``'s non-structure points on ``tgt`` under ``T (4, 4)`` (``T_tgt_src``):
    shares within ``radius`` of a target representative (:class:`ClutterFit`; NaN where a
    part is empty)."""
    from pykdtree.kdtree import KDTree

    T = np.asarray(T, dtype=np.float64)
    moved = src.points @ T[:3, :3].T + T[:3, 3]
    near = KDTree(tgt.points).query(moved, k=1)[0] < radius
    rest = tgt.points[~tgt.mask]
    if len(rest):
        near_rest = KDTree(rest).query(moved, k=1)[0] < radius
    else:
        near_rest = np.zeros(len(moved), dtype=bool)
    clutter = ~src.mask

    def share(hit: np.ndarray, where: np.ndarray) -> float:
        return float(hit[where].mean()) if where.any() else math.nan

    return ClutterFit(
        clutter=share(near, clutter),
        clutter_to_clutter=share(near_rest, clutter),
        structure=share(near, src.mask),
        overall=float(near.mean()),
        clutter_share=float(clutter.mean()),
    )


def clutter_shares(
    src: Structure, tgt: Structure, transforms: list[np.ndarray], radius: float
) -> np.ndarray:
    """``(K,)`` :attr:`ClutterFit.clutter` of ``src`` on ``tgt`` under each of ``transforms``
    (``(4, 4)`` each), on one search tree of the target (NaN without clutter)."""
    from pykdtree.kdtree import KDTree

    clutter = src.points[~src.mask]
    if not len(clutter):
        return np.full(len(transforms), math.nan)
    tree = KDTree(tgt.points)
    out = []
    for T in transforms:
        T = np.asarray(T, dtype=np.float64)
        moved = clutter @ T[:3, :3].T + T[:3, 3]
        out.append(float((tree.query(moved, k=1, distance_upper_bound=radius)[0] < radius).mean()))
    return np.array(out)


def turned_alternatives(
    src: Structure,
    tgt: Structure,
    T: np.ndarray,
    voxel_size: float,
    degrees: tuple[float, ...] = (90.0, 180.0, 270.0),
    correlate: bool = False,
) -> list[np.ndarray]:
    """``T (4, 4)`` turned by each of ``degrees`` about the target's up axis through the
    moved source's centre, then moved so that the source's large planes overlay the target's
    along each main direction (:func:`_plane_shift`): where a room turned onto itself would
    put the source, one ``(4, 4)`` per turn. With ``correlate``, each turn is followed by a
    second one moved by :func:`correlation_shift` instead (cells of
    :data:`CORRELATION_CELL` voxels): where the turned source overlays the most of the whole
    target (a room whose walls the source sees in part, which the planes alone misplace)."""
    from byoc_cli.geometry.orientation import turn_about

    T = np.asarray(T, dtype=np.float64)
    up = tgt.directions[tgt.up]
    moved = src.points @ T[:3, :3].T + T[:3, 3]
    normals = src.normals @ T[:3, :3].T
    centre = moved.mean(axis=0)
    out, turned = [], []
    for deg in degrees:
        turn = turn_about(up, deg, centre)
        p = (moved @ turn[:3, :3].T + turn[:3, 3])[src.mask]
        n = (normals @ turn[:3, :3].T)[src.mask]
        move = np.eye(4)
        move[:3, 3] = _plane_shift(
            p, n, tgt.points[tgt.mask], tgt.normals[tgt.mask], tgt.directions, voxel_size
        )
        out.append(move @ turn @ T)
        turned.append(turn @ T)
    if correlate:
        sources = [src.points @ U[:3, :3].T + U[:3, 3] for U in turned]
        for U, shift in zip(
            turned, correlation_shifts(sources, tgt.points, voxel_size), strict=True
        ):
            move = np.eye(4)
            move[:3, 3] = shift
            out.append(move @ U)
    return out


def correlation_shifts(
    sources: list[np.ndarray], q: np.ndarray, voxel_size: float
) -> list[np.ndarray]:
    """``(3,)`` for each of ``sources`` (``(P, 3)`` arrays), the translation that lays its
    most occupied cells on occupied cells of ``q (Q, 3)``: the peak of the cross-correlation
    of their occupancy grids (cubes of :data:`CORRELATION_CELL` voxels, by FFT), in whole
    cells. The grids span the middle of the points (their :data:`CORRELATION_SPAN`
    percentiles: a stray point far away is left out) and hold at most
    :data:`CORRELATION_CELLS` cells (a wider span takes coarser cells; zeros past the float
    range); the target's is transformed once."""
    boxes = [np.percentile(x, CORRELATION_SPAN, axis=0) for x in (q, *sources)]
    cell = CORRELATION_CELL * voxel_size
    lo = np.min([b[0] for b in boxes], axis=0) - cell
    hi = np.max([b[1] for b in boxes], axis=0) + cell
    cell = max(cell, float(np.prod(hi - lo) / CORRELATION_CELLS) ** (1.0 / 3.0))
    if not np.isfinite(cell) or not np.all(np.isfinite(lo)):  # a span past float range
        return [np.zeros(3) for _ in sources]
    shape = np.ceil((hi - lo) / cell).astype(np.int64) + 1
    size = tuple(int(n) for n in 2 * shape - 1)  # every lag, none wrapped around

    def spectrum(points: np.ndarray) -> np.ndarray:
        keep = np.all((points >= lo) & (points < hi), axis=1)
        cells = np.floor((points[keep] - lo) / cell).astype(np.int64)
        grid = np.zeros(size, dtype=np.float32)
        grid[tuple(cells.T)] = 1.0
        return np.fft.rfftn(grid, axes=(0, 1, 2))

    target = spectrum(q)
    shifts = []
    for points in sources:
        correlation = np.fft.irfftn(target * np.conj(spectrum(points)), size, axes=(0, 1, 2))
        lag = np.array(np.unravel_index(int(np.argmax(correlation)), size))
        lag = np.where(lag >= shape, lag - np.array(size), lag)
        shifts.append(lag * cell)
    return shifts


def _plane_shift(p, n, q, m, directions, voxel_size) -> np.ndarray:
    """``(3,)`` the translation that overlays the plane points ``p (P, 3)`` (normals ``n``)
    on ``q (Q, 3)`` (normals ``m``): along each of ``directions (D, 3)``, the shift that
    best correlates the histograms (bins of ``voxel_size``) of the offsets of the points whose
    normal lies along it; least squares over the directions (zero when none has points)."""
    cone = math.cos(math.radians(STRUCTURE_CONE_DEG))
    rows, shifts = [], []
    for d in directions:
        a = p[np.abs(n @ d) > cone] @ d
        b = q[np.abs(m @ d) > cone] @ d
        if len(a) == 0 or len(b) == 0:
            continue
        lo = min(a.min(), b.min())
        size = int((max(a.max(), b.max()) - lo) / voxel_size) + 1
        ha = np.bincount(((a - lo) / voxel_size).astype(np.int64), minlength=size)
        hb = np.bincount(((b - lo) / voxel_size).astype(np.int64), minlength=size)
        rows.append(d)
        shifts.append((int(np.argmax(_correlation(hb, ha))) - (size - 1)) * voxel_size)
    if not rows:
        return np.zeros(3)
    return np.linalg.lstsq(np.array(rows), np.array(shifts), rcond=None)[0]


def _correlation(h: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``np.correlate(h, g, "full")`` of two count histograms of one length ``L`` (``(2L - 1,)``,
    lag ``-(L - 1)`` first) by FFT: O(L log L) where a stray point far out makes ``L`` large,
    rounded to the integers the counts give."""
    L = len(h)
    n = 1 << (2 * L - 1).bit_length()
    circular = np.fft.irfft(np.fft.rfft(h, n) * np.conj(np.fft.rfft(g, n)), n)
    lags = np.concatenate([circular[n - (L - 1) :], circular[:L]])  # -(L-1) .. L-1
    return np.rint(lags)
