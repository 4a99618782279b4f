"""A cloud's up axis and turns about it: what the learned features need to see a source turned
the way the target is (:mod:`byoc_cli.pipeline.turns`).

The up axis is read from the surfaces: of the directions many surface normals lie along, the
one the cloud is thinnest along (:func:`up_axis`). On rooms (floor and ceiling against walls
farther apart), streets and desks it is the vertical, up to a sign a turn about it does not
need.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.transforms import axis_angle_to_matrix

#: normals sampled for the up axis, and the neighbours each is fitted to
UP_SAMPLES, UP_NEIGHBOURS = 2000, 16
#: a main surface direction holds at least this share of the normals within UP_CONE_DEG of it,
#: and lies at least UP_APART_DEG from the others
UP_MIN_SHARE, UP_CONE_DEG, UP_APART_DEG = 0.08, 10.0, 45.0


def up_axis(
    points: np.ndarray, generator: torch.Generator | None = None, samples: int = UP_SAMPLES
) -> np.ndarray:
    """The up axis of ``points (N, 3)``, ``(3,)`` unit: of the directions many surface normals
    lie along, the one the cloud is thinnest along.

    The normal at each of a seeded random subset of ``samples`` points is the least spread
    direction of its :data:`UP_NEIGHBOURS` nearest points (k-d tree). The main directions are
    found greedily: the normal with the most normals within :data:`UP_CONE_DEG` of it (either
    sign), refined to their mean, then the next one at least :data:`UP_APART_DEG` from those
    found, while one holds at least :data:`UP_MIN_SHARE` of the normals (a room's floor and
    ceiling, its walls). The up axis is the main direction along which the sampled points
    spread least (a room is lower than it is wide, a street's ground is flat); the strongest
    one when only it is found.

    Args:
        points: ``(N, 3)`` finite, ``N >= 3``.
        generator: draws the subset (default: seed 0).
        samples: normals at most.

    Returns:
        ``(3,)`` float64 of unit length; its sign is that of its largest component.

    Raises:
        ShapeError: ``points`` is not ``(N, 3)`` with ``N >= 3``.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise ShapeError(f"points must be (N, 3) with N >= 3, got {tuple(pts.shape)}")
    generator = generator or torch.Generator().manual_seed(0)
    asked = pts[torch.randperm(len(pts), generator=generator)[: min(samples, len(pts))].numpy()]
    main = np.stack(main_directions(point_normals(pts, asked)))
    axis = main[thinnest(asked, main)]
    return axis if axis[np.argmax(np.abs(axis))] > 0 else -axis


def thinnest(points: np.ndarray, directions: np.ndarray) -> int:
    """The index of the one of ``directions (D, 3)`` along which ``points (N, 3)`` spread
    least (standard deviation of their offsets)."""
    return int(np.argmin(((points - points.mean(axis=0)) @ directions.T).std(axis=0)))


def point_normals(points: np.ndarray, asked: np.ndarray) -> np.ndarray:
    """``(S, 3)`` the least spread direction of the :data:`UP_NEIGHBOURS` nearest ``points``
    of each of ``asked (S, 3)`` (k-d tree)."""
    from pykdtree.kdtree import KDTree

    k = min(UP_NEIGHBOURS, len(points))
    _, idx = KDTree(points).query(asked, k=k)
    near = points[np.asarray(idx).reshape(len(asked), k)]  # (S, k, 3)
    centred = near - near.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("ski,skj->sij", centred, centred))
    return vectors[:, :, 0]


def main_directions(normals: np.ndarray) -> list[np.ndarray]:
    """The main directions of ``normals (S, 3)`` (:func:`up_axis`), strongest first; at
    least one."""
    cone = math.cos(math.radians(UP_CONE_DEG))
    apart = math.cos(math.radians(UP_APART_DEG))
    close = np.abs(normals @ normals.T) > cone  # (S, S)
    free = np.ones(len(normals), dtype=bool)
    found: list[np.ndarray] = []
    while True:
        support = (close & free[None, :]).sum(axis=1) * free
        best = int(np.argmax(support))
        if found and support[best] < UP_MIN_SHARE * len(normals):
            return found
        members = normals[close[best]]
        signed = members * np.sign(members @ normals[best])[:, None]
        direction = signed.sum(axis=0)
        found.append(direction / np.linalg.norm(direction))
        free &= np.abs(normals @ found[-1]) < apart
        if len(found) == 3 or not free.any():
            return found


def turn_about(axis: np.ndarray, degrees: float, centre: np.ndarray) -> np.ndarray:
    """``(4, 4)`` float64: the rotation of ``degrees`` about ``axis (3,)`` through ``centre
    (3,)``, on column vectors.

    Raises:
        ShapeError: ``axis`` or ``centre`` is not ``(3,)``, or ``axis`` is zero.
    """
    k = np.asarray(axis, dtype=np.float64)
    c = np.asarray(centre, dtype=np.float64)
    if k.shape != (3,) or c.shape != (3,) or not np.linalg.norm(k) > 0:
        raise ShapeError(f"axis and centre must be (3,) and the axis non-zero, got {k}, {c}")
    turn = torch.from_numpy(k / np.linalg.norm(k) * math.radians(degrees))
    T = np.eye(4)
    T[:3, :3] = axis_angle_to_matrix(turn).numpy()
    T[:3, 3] = c - T[:3, :3] @ c
    return T


def aligning(axis: np.ndarray, onto: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``(4, 4)`` float64: the smallest rotation that turns the direction ``axis (3,)`` onto
    ``onto (3,)``, about ``centre (3,)`` (the identity for parallel directions), on column
    vectors.

    Raises:
        ShapeError: a direction is zero or points opposite the other (no smallest rotation),
            or a vector is not ``(3,)``.
    """
    a = np.asarray(axis, dtype=np.float64)
    b = np.asarray(onto, dtype=np.float64)
    if a.shape != (3,) or b.shape != (3,) or not (np.linalg.norm(a) > 0 and np.linalg.norm(b) > 0):
        raise ShapeError(f"axis and onto must be non-zero (3,) vectors, got {a}, {b}")
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    cross = np.cross(a, b)
    sine, cosine = float(np.linalg.norm(cross)), float(a @ b)
    if sine < 1e-12:
        if cosine < 0:
            raise ShapeError(f"axis {a} points opposite {b}: no smallest rotation between them")
        return turn_about(a, 0.0, centre)
    return turn_about(cross / sine, math.degrees(math.atan2(sine, cosine)), centre)
