"""One RGB-D frame: its record, the reasons it can be dropped or fail, and image decoding.

Decoding maps every failure (file gone, not an image, wrong pixel format, truncated) to
:class:`FrameError`, which data loaders catch, count and replace by another sample.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from byoc_cli.errors import DatasetError, InputError
from byoc_cli.io.inputs import check_input

#: Raw value that marks a missing measurement in 16-bit depth images (raw 7-Scenes).
INVALID_DEPTH_16 = 65535
_DEPTH_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I", "F")


class FrameError(DatasetError):
    """One frame of a sequence cannot be read (file gone, corrupt, wrong format or size).

    Raised at read time by :meth:`RGBDSequence.read_depth` / :meth:`RGBDSequence.read_color`;
    a data loader catches it, counts the frame as skipped and moves on.

    Args:
        path: the offending image.
        problem: what is wrong with it.
        frame: position of the frame in :attr:`RGBDSequence.frames`.
    """

    def __init__(self, path: object, problem: str, frame: int | None = None) -> None:
        self.frame = frame
        super().__init__(path, problem)


class RGBDFrame(NamedTuple):
    """One frame of an RGB-D video.

    Attributes:
        index: the frame's number in its source: the file number (3DMatch ``frame-XXXXXX``,
            ScanNet ``N``), or the position in the depth listing (TUM ``depth.txt``, Redwood's
            sorted ``depth/``). Reads take the position in :attr:`RGBDSequence.frames`.
        depth_path: the depth image.
        color_path: the colour image, or None.
        pose: ``(4, 4)`` float64 camera-to-world ``T_world_cam``, or None.
        timestamp: seconds (TUM), else None.
    """

    index: int
    depth_path: Path
    color_path: Path | None
    pose: np.ndarray | None
    timestamp: float | None


class SkippedFrame(NamedTuple):
    """A frame (or listed image) dropped at discovery.

    Attributes:
        item: the file or listing entry.
        reason: why, as a short phrase.
    """

    item: str
    reason: str


def open_image(path: Path, frame: int | None):
    """Open an image with pillow (lazily), mapping every failure to :class:`FrameError`."""
    from PIL import Image, UnidentifiedImageError

    try:
        check_input(path, "image")  # a FIFO or a device is never opened
    except InputError as exc:
        raise FrameError(path, exc.problem, frame) from exc
    try:
        return Image.open(path)
    except FileNotFoundError as exc:
        raise FrameError(path, "file not found", frame) from exc
    except UnidentifiedImageError as exc:
        raise FrameError(path, "not an image file (pillow cannot identify it)", frame) from exc
    except (OSError, SyntaxError, ValueError) as exc:
        raise FrameError(path, f"cannot open image ({exc})", frame) from exc


def image_shape(path: Path, frame: int | None = None) -> tuple[int, int]:
    """``(H, W)`` of an image from its header.

    Raises:
        FrameError: the file is gone or not an image.
    """
    with open_image(path, frame) as image:
        width, height = image.size
    return int(height), int(width)


def read_depth_png(path: Path, depth_scale: float, frame: int | None = None) -> np.ndarray:
    """16-bit (or 32-bit int / float) depth image -> ``(H, W)`` float32 metres, 0 = invalid.

    Args:
        path: the image.
        depth_scale: raw units per metre.
        frame: position of the frame, for the error.

    Returns:
        ``(H, W)`` float32; 0 where raw depth is 0 or 65535 (integer images) or non-finite
        or negative (float images).

    Raises:
        FrameError: the file is gone, corrupt or not a single-channel depth image.
    """
    with open_image(path, frame) as image:
        if image.mode not in _DEPTH_MODES:
            raise FrameError(
                path,
                f"not a depth image (pixel format {image.mode!r}; expected 16-bit grayscale)",
                frame,
            )
        try:
            raw = np.asarray(image)
        except (OSError, SyntaxError, ValueError) as exc:
            raise FrameError(path, f"truncated or corrupt image ({exc})", frame) from exc
    if raw.ndim != 2:
        raise FrameError(path, f"not a depth image (array of shape {raw.shape})", frame)
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    if raw.dtype.kind == "f":
        invalid = ~np.isfinite(depth) | (depth < 0)
    else:
        invalid = (raw <= 0) | (raw == INVALID_DEPTH_16)
    depth[invalid] = 0.0
    return depth


def read_color_image(path: Path, shape: tuple[int, int], frame: int | None = None) -> np.ndarray:
    """Colour image -> ``(H, W, 3)`` uint8 RGB at ``shape`` (bilinear resize when needed).

    Raises:
        FrameError: the file is gone or corrupt.
    """
    from PIL import Image

    height, width = shape
    with open_image(path, frame) as image:
        try:
            rgb = image.convert("RGB")
            if rgb.size != (width, height):
                rgb = rgb.resize((width, height), Image.Resampling.BILINEAR)
            array = np.asarray(rgb, dtype=np.uint8)
        except (OSError, SyntaxError, ValueError) as exc:
            raise FrameError(path, f"truncated or corrupt image ({exc})", frame) from exc
    return np.ascontiguousarray(array)
