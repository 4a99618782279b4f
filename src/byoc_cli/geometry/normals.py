"""Surface normals of voxel averages from the moments of the cells around each point.

A point's normal is the least-variance direction of the points in the 3 x 3 x 3 cells around
its cell (one normal per cell, shared by its points), widened where that box holds too few
points; the covariances come from per-cell sums of the points' first and second moments, so a
cloud costs one sort of its cell keys per cell size. The cells and keys are those of
:mod:`byoc_cli.geometry.neighbors`. Shapes: points ``(N, 3)`` float64 metres.
"""

from __future__ import annotations

import math

import torch

from byoc_cli.geometry.neighbors import (
    DenseCells,
    _cells,
    cell_keys,
    grid_origin,
    neighbor_positions,
)

#: the widenings of the box where it holds fewer than ``min_points`` points, in cells
WIDER = (2.0, 4.0, 8.0)


def surface_normals(points: torch.Tensor, size: float, min_points: int = 8) -> torch.Tensor:
    """Unit normals ``(N, 3)`` of ``points (N, 3)``: the least-variance direction of the
    points in the 27 cells of ``size`` around each point's cell (a box 3 cells wide; one
    normal per cell, shared by its points). Where that box holds fewer than ``min_points``
    points (sparse samples: a few points fit any plane) the box of twice the cell is used,
    and so on up to 8 times the cell. The sign is arbitrary."""
    normals, count = _cell_normals(points, size)
    centre = points.mean(dim=0) if len(points) else points.new_zeros(3)
    for scale in WIDER:
        weak = count < min_points
        if not bool(weak.any()):
            break
        wider, wider_count = _cell_normals(points[weak], size * scale, points, centre)
        normals[weak], count[weak] = wider, wider_count
    return normals


def _cell_normals(
    queries: torch.Tensor,
    size: float,
    points: torch.Tensor | None = None,
    centre: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Normals ``(Q, 3)`` of the 27-cell boxes around ``queries (Q, 3)`` from the moments of
    ``points (N, 3)`` (default: the queries) about ``centre (3,)`` (default: their mean), and
    how many points each box holds ``(Q,)``. Of other ``points`` only those in the queries'
    boxes are summed: the same sums, in the same order, as over all of them."""
    own_points = points is None
    points = queries if own_points else points
    origin = grid_origin(points, size)
    if centre is None:
        centre = points.mean(dim=0) if len(points) else points.new_zeros(3)
    own = _cells(queries, size, origin)
    q_uniq, q_inverse = torch.unique(cell_keys(own), return_inverse=True)
    q_cells = torch.zeros(len(q_uniq), 3, dtype=torch.int64)
    q_cells.index_copy_(0, q_inverse, own)
    if own_points:  # the queries' cells are the points'
        uniq, inverse, cells = q_uniq, q_inverse, q_cells
    else:
        point_cells = _cells(points, size, origin)
        points, point_cells = _in_boxes(points, point_cells, q_uniq)
        uniq, inverse = torch.unique(cell_keys(point_cells), return_inverse=True)
        cells = torch.zeros(len(uniq), 3, dtype=torch.int64).index_copy_(0, inverse, point_cells)
    C = len(uniq)
    p = points - centre
    moments = torch.zeros(C + 1, 10, dtype=points.dtype)  # row C: an empty cell
    moments[:C, 0].index_add_(0, inverse, torch.ones(len(p), dtype=points.dtype))
    moments[:C, 1:4].index_add_(0, inverse, p)
    x, y, z = p.unbind(dim=1)
    products = torch.stack([x * x, x * y, x * z, y * y, y * z, z * z], dim=1)
    moments[:C, 4:].index_add_(0, inverse, products)
    # the boxes: around each occupied cell of the queries (a dense table where it fits)
    dense = DenseCells.build(cells, torch.arange(C), 1) if C else None
    pos = dense.lookup(q_cells, 1) if dense is not None else neighbor_positions(uniq, q_cells)
    # one row of cells per offset, gathered with index_select: faster than indexing with a
    # column of pos, and the same sums in the same order
    offsets = torch.where(pos >= 0, pos, C).T.contiguous()  # (27, Q)
    total = moments.index_select(0, offsets[0])
    for k in range(1, 27):
        total += moments.index_select(0, offsets[k])
    n = total[:, 0].clamp_min(1.0)
    mean = total[:, 1:4] / n[:, None]
    xx, xy, xz, yy, yz, zz = (total[:, 4 + i] / n for i in range(6))
    cov = (
        torch.stack(
            [
                torch.stack([xx, xy, xz], dim=1),
                torch.stack([xy, yy, yz], dim=1),
                torch.stack([xz, yz, zz], dim=1),
            ],
            dim=1,
        )
        - mean[:, :, None] * mean[:, None, :]
    )
    return smallest_eigenvector(cov)[q_inverse], total[:, 0][q_inverse]


def _in_boxes(
    points: torch.Tensor, cells: torch.Tensor, box_keys: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``points (N, 3)`` (and their ``cells (N, 3)``) that lie in the 27 cells around any
    of the cells ``box_keys (B,)``, in their order. A key is ``x 2^42 + y 2^21 + z``, so a
    neighbour's key is the cell's plus an offset (one that wraps past an edge of the grid
    names a cell no point is in)."""
    span = torch.arange(-1, 2)
    dx, dy, dz = (d.reshape(-1) for d in torch.meshgrid(span, span, span, indexing="ij"))
    wanted = torch.unique(box_keys[:, None] + ((dx << 42) + (dy << 21) + dz))
    if len(wanted) == 0:
        return points[:0], cells[:0]
    keys = cell_keys(cells)
    at = torch.searchsorted(wanted, keys).clamp_max(len(wanted) - 1)
    inside = wanted[at] == keys
    return points[inside], cells[inside]


def smallest_eigenvector(A: torch.Tensor) -> torch.Tensor:
    """Unit eigenvectors ``(B, 3)`` of the smallest eigenvalue of symmetric ``A (B, 3, 3)``,
    in closed form (several times faster than ``torch.linalg.eigh`` on many small
    matrices): the eigenvalue by the trigonometric solution of the characteristic cubic,
    the vector as the longest cross product of two rows of ``A - lambda I``. Where that is
    ill-defined (a nearly isotropic ``A``, or an exact double root) ``eigh`` decides."""
    a00, a01, a02 = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    a11, a12, a22 = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    q = (a00 + a11 + a22) / 3
    p1 = a01**2 + a02**2 + a12**2
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2 * p1
    p = torch.sqrt(p2 / 6).clamp_min(1e-300)
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    det = (
        b00 * (b11 * b22 - b12 * b12)
        - b01 * (b01 * b22 - b12 * b02)
        + b02 * (b01 * b12 - b11 * b02)
    )
    phi = torch.acos((det / 2).clamp(-1.0, 1.0)) / 3
    smallest = q + 2 * p * torch.cos(phi + 2 * math.pi / 3)
    eye = torch.eye(3, dtype=A.dtype)
    M = A - smallest[:, None, None] * eye
    crosses = torch.stack(
        [
            torch.linalg.cross(M[:, 0], M[:, 1]),
            torch.linalg.cross(M[:, 0], M[:, 2]),
            torch.linalg.cross(M[:, 1], M[:, 2]),
        ],
        dim=1,
    )  # (B, 3, 3)
    norms = crosses.norm(dim=2)
    best, pick = norms.max(dim=1)
    vector = crosses[torch.arange(len(A)), pick] / best.clamp_min(1e-300)[:, None]
    # ill-conditioned: the rows of A - lambda I nearly parallel (or A nearly isotropic)
    scale = (p * p).clamp_min(1e-300)
    shaky = (best < 1e-6 * scale) | (p2 < 1e-24 * (q * q).clamp_min(1e-300))
    if bool(shaky.any()):
        vector[shaky] = torch.linalg.eigh(A[shaky]).eigenvectors[:, :, 0]
    return vector
