"""Small synthetic scans for the initial-pose tests of register-scans: a room of boxes seen
from a few stations, with their true poses, and guesses of those poses."""

from __future__ import annotations

import math

import numpy as np

#: a room 3 x 2.4 x 2 m with two boxes on its floor (the boxes make every pose unique)
ROOM = [([-1.5, -1.2, 0.0], [1.5, 1.2, 2.0]), ([-0.4, -0.3, 0.0], [0.3, 0.2, 0.7])]
ROOM.append(([0.6, 0.4, 0.0], [1.2, 1.0, 1.1]))
#: the same room with two equal boxes placed point-symmetrically: a half turn about the
#: vertical axis through the room's middle maps it onto itself
SYMMETRIC = [ROOM[0], ([0.5, 0.3, 0.0], [1.0, 0.8, 0.9]), ([-1.0, -0.8, 0.0], [-0.5, -0.3, 0.9])]


def turn_z(degrees: float, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``(4, 4)``: a turn about z, then ``shift``."""
    a = math.radians(degrees)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[:3, 3] = shift
    return T


#: the stations' true poses T_world_scan (scan 0 is the world)
STATIONS = [np.eye(4), turn_z(25.0, (0.3, -0.2, 0.05)), turn_z(-30.0, (-0.2, 0.3, 0.0))]


def sample_boxes(boxes: list, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n * len(boxes), 3)`` points on the faces of the boxes ``(low, high)``."""
    out = []
    for lo, hi in boxes:
        lo, hi = np.array(lo), np.array(hi)
        p = lo + rng.random((n, 3)) * (hi - lo)
        face = rng.integers(0, 6, n)
        axis = face // 2
        p[np.arange(n), axis] = np.where(face % 2 == 0, lo[axis], hi[axis])
        out.append(p)
    return np.concatenate(out)


def scans(boxes=ROOM, poses=STATIONS, n: int = 6000, seed: int = 2) -> list[np.ndarray]:
    """The room sampled anew from each station, each in its own frame."""
    rng = np.random.default_rng(seed)
    return [(sample_boxes(boxes, n, rng) - P[:3, 3]) @ P[:3, :3] for P in poses]


def perturbed(pose: np.ndarray, degrees: float, metres: float, rng) -> np.ndarray:
    """``pose`` moved in its own frame by a turn of ``degrees`` about a random axis and a
    shift of ``metres`` in a random direction."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = math.radians(degrees)
    D = np.eye(4)
    D[:3, :3] = np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K
    step = rng.normal(size=3)
    D[:3, 3] = metres * step / np.linalg.norm(step)
    return pose @ D


def guesses(degrees: float, metres: float, seed: int = 0, world=None) -> list[np.ndarray]:
    """The stations' poses in another world (``world @ P``, default a turn and a far shift),
    every one but the first perturbed by ``degrees`` and ``metres``."""
    rng = np.random.default_rng(seed)
    world = turn_z(40.0, (10.0, -3.0, 1.5)) if world is None else world
    return [world @ STATIONS[0]] + [
        world @ perturbed(P, degrees, metres, rng) for P in STATIONS[1:]
    ]


#: the source's pose in the target's frame of :func:`seen_twice` (a room scanned twice)
SEEN_TWICE = turn_z(30.0, (0.2, -0.1, 0.0))


def seen_twice(n: int = 6000) -> tuple[np.ndarray, np.ndarray]:
    """``(source, target)`` scans of :data:`ROOM`, the source at :data:`SEEN_TWICE`, each
    ``(n, 3)`` with its own noise."""
    src = scans(ROOM, [np.eye(4), SEEN_TWICE], n=n)[1]
    tgt = scans(ROOM, [np.eye(4)], n=n, seed=5)[0]
    return src, tgt
