"""A tiny synthetic posed depth sequence: a box on the floor of a closed room, rendered exactly.

The room is the inside of the box ``ROOM``; a solid box ``BLOCK`` stands in it. Depth is ray
cast analytically (slab method) through pixel centres, so every depth pixel lies on one of the
two boxes' surfaces; :func:`surface_distance` is the exact distance of a point to them. The
sequence is written in the 3DMatch RGB-D layout (``camera-intrinsics.txt``,
``seq-01/frame-XXXXXX.depth.png`` in millimetres, ``frame-XXXXXX.pose.txt`` camera-to-world).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

WIDTH, HEIGHT = 64, 48
K = np.array([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])
#: (min corner, max corner) in metres, world frame (y up).
ROOM = (np.array([-1.2, 0.0, -1.2]), np.array([1.2, 1.6, 1.2]))
BLOCK = (np.array([-0.3, 0.0, -0.25]), np.array([0.25, 0.45, 0.3]))


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) at ``eye``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def orbit_poses(count: int, radius: float = 0.9, height: float = 1.0) -> np.ndarray:
    """``(count, 4, 4)`` poses on an arc around the block, looking at it (15 deg per 5)."""
    angles = np.deg2rad(np.linspace(0.0, 3.0 * count, count))
    eyes = np.stack([radius * np.sin(angles), np.full(count, height), radius * np.cos(angles)], 1)
    return np.stack([look_at(e, np.array([0.0, 0.2, 0.0])) for e in eyes])


def _slab(origin: np.ndarray, direction: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / direction
        t0 = (box[0] - origin) * inv
        t1 = (box[1] - origin) * inv
    return np.minimum(t0, t1).max(axis=1), np.maximum(t0, t1).min(axis=1)


def render_depth(pose: np.ndarray) -> np.ndarray:
    """``(H, W)`` float64 depth (z in the camera) of the scene seen from ``pose``."""
    u, v = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ np.linalg.inv(K).T  # z = 1
    direction = rays @ pose[:3, :3].T
    origin = np.broadcast_to(pose[:3, 3], direction.shape)
    _, room_exit = _slab(origin, direction, ROOM)
    block_in, block_out = _slab(origin, direction, BLOCK)
    hit_block = (block_in <= block_out) & (block_in > 0)
    t = np.where(hit_block, block_in, room_exit)
    return t.reshape(HEIGHT, WIDTH)  # t along a ray with z = 1 in the camera is the depth


def _box_surface_distance(points: np.ndarray, box) -> np.ndarray:
    lo, hi = box
    outside = np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=1)
    inside = np.minimum(points - lo, hi - points).min(axis=1)  # >= 0 inside the box
    return np.where(outside > 0, outside, inside)


def surface_distance(points_world: np.ndarray) -> np.ndarray:
    """``(N,)`` exact distance of world points to the nearest surface of the scene."""
    return np.minimum(
        _box_surface_distance(points_world, ROOM), _box_surface_distance(points_world, BLOCK)
    )


def write_sequence(root: Path, poses: np.ndarray, *, with_poses: bool = True) -> Path:
    """Write the rendered sequence in the 3DMatch RGB-D layout; returns ``root``."""
    seq = root / "seq-01"
    seq.mkdir(parents=True)
    np.savetxt(root / "camera-intrinsics.txt", K)
    for k, pose in enumerate(poses):
        depth_mm = np.rint(render_depth(pose) * 1000.0).astype(np.uint16)
        Image.fromarray(depth_mm).save(seq / f"frame-{k:06d}.depth.png")
        if with_poses:
            np.savetxt(seq / f"frame-{k:06d}.pose.txt", pose)
    return root
