"""The 128x128 frame preprocessing of the paper's variants (docs/training.md): centre crop,
resize, intrinsics."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from byoc_cli.errors import ShapeError


class PreprocessedFrame(NamedTuple):
    """Output of :func:`preprocess_frame`.

    Attributes:
        depth: ``(S, S)`` float32 metres, 0 = invalid.
        color: ``(S, S, 3)`` float32 in [-1, 1], or None.
        K: ``(3, 3)`` float64 intrinsics of the ``S x S`` images.
    """

    depth: np.ndarray
    color: np.ndarray | None
    K: np.ndarray


def preprocess_frame(
    depth_m: np.ndarray, color: np.ndarray | None, K: np.ndarray, size: int = 128
) -> PreprocessedFrame:
    """Centre-crop a frame to a square and resize it to ``size x size`` (docs/training.md).

    Depth: the centre square (side ``min(H, W)``) resized with nearest neighbour (output pixel
    centre ``c`` reads the source pixel that contains ``c``). Colour: the SAME square resized
    bilinearly (antialiased when shrinking), then mapped to [-1, 1]. This equals "resize the
    short side to ``size``, centre-crop" up to rounding, but keeps colour and depth pixels
    exactly aligned. Intrinsics: ``cx`` (``cy`` for portrait images) shifted by the crop
    offset, then ``fx, s, cx, fy, cy`` scaled by ``size / side``.

    Args:
        depth_m: ``(H, W)`` depth in metres, 0 = invalid.
        color: ``(H, W, 3)`` uint8 RGB at the depth resolution, or None.
        K: ``(3, 3)`` intrinsics of the ``H x W`` images.
        size: output side.

    Returns:
        :class:`PreprocessedFrame` ``(depth (S, S) float32, color (S, S, 3) float32 in
        [-1, 1] or None, K (3, 3) float64)``.

    Raises:
        ShapeError: ``depth_m`` not 2-D, ``color`` not ``(H, W, 3)`` uint8, ``K`` not 3x3.
        ValueError: ``size < 1``.
    """
    from PIL import Image

    depth_m = np.asarray(depth_m)
    K = np.asarray(K, dtype=np.float64)
    size = int(size)
    if depth_m.ndim != 2 or depth_m.size == 0:
        raise ShapeError(f"depth_m must be a non-empty (H, W) array, got shape {depth_m.shape}")
    if K.shape != (3, 3):
        raise ShapeError(f"K must be (3, 3), got {K.shape}")
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    height, width = depth_m.shape
    side = min(height, width)
    x0, y0 = (width - side) // 2, (height - side) // 2

    # floor((k + 0.5) * side / size) in exact integer arithmetic: a centre that lands on a
    # source pixel's edge belongs to that pixel (floating point could round it to the left)
    src = np.minimum((2 * np.arange(size, dtype=np.int64) + 1) * side // (2 * size), side - 1)
    depth = depth_m[y0 + src[:, None], x0 + src[None, :]].astype(np.float32)
    with np.errstate(invalid="ignore"):
        depth[~(np.isfinite(depth) & (depth > 0))] = 0.0

    color_out = None
    if color is not None:
        color = np.asarray(color)
        if color.shape != (height, width, 3) or color.dtype != np.uint8:
            raise ShapeError(
                f"color must be ({height}, {width}, 3) uint8 like the depth, got "
                f"{color.shape} {color.dtype}"
            )
        image = Image.fromarray(np.ascontiguousarray(color), mode="RGB")
        image = image.resize(
            (size, size), Image.Resampling.BILINEAR, box=(x0, y0, x0 + side, y0 + side)
        )
        color_out = np.asarray(image, dtype=np.float32) / np.float32(127.5) - np.float32(1.0)

    K_new = K.copy()
    K_new[0, 2] -= x0
    K_new[1, 2] -= y0
    K_new[:2] *= size / side
    return PreprocessedFrame(np.ascontiguousarray(depth), color_out, K_new)
