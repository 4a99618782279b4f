"""Back-projection of a depth image to a camera-frame point cloud.

OpenCV camera axes (x right, y down, z forward); a pixel ``(u, v)`` is column ``u``, row ``v``,
back-projected through its centre ``(u + 0.5, v + 0.5)``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class BackProjection(NamedTuple):
    """Output of :func:`backproject`.

    Attributes:
        points: ``(N, 3)`` float32 camera-frame points in metres.
        pixel_index: ``(N,)`` int64 row-major pixel of each point, ``v * W + u``.
    """

    points: np.ndarray
    pixel_index: np.ndarray


def backproject(depth_m: np.ndarray, K: np.ndarray) -> BackProjection:
    """Back-project a depth image through pixel centres, dropping missing depth.

    Pixel ``(u, v)`` with depth ``z > 0`` gives ``z * K^-1 [u + 0.5, v + 0.5, 1]`` (OpenCV
    axes). Points come in row-major pixel order; ``pixel_index = v * W + u`` lets each point
    read its own pixel of an ``(H, W)`` feature map.

    Args:
        depth_m: ``(H, W)`` depth in metres; ``<= 0`` and non-finite are missing.
        K: ``(3, 3)`` intrinsics.

    Returns:
        :class:`BackProjection` ``(points (N, 3) float32, pixel_index (N,) int64)``.

    Raises:
        ShapeError: ``depth_m`` not 2-D or ``K`` not 3x3.
        ValueError: ``K`` not finite and invertible.
    """
    from byoc_cli.io.depth import valid_depth

    depth_m, K, valid = valid_depth(depth_m, K)
    pixel_index = np.flatnonzero(valid).astype(np.int64)
    v, u = np.divmod(pixel_index, depth_m.shape[1])
    z = depth_m.reshape(-1)[pixel_index].astype(np.float64)
    rays = np.stack([u + 0.5, v + 0.5, np.ones_like(z)], axis=1) @ np.linalg.inv(K).T
    return BackProjection((rays * z[:, None]).astype(np.float32), pixel_index)
