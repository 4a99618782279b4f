"""One continuous RGB-D video: its frames, intrinsics and depth scale, and frame reads."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from byoc_cli.io.rgbd.frames import (
    FrameError,
    RGBDFrame,
    SkippedFrame,
    image_shape,
    read_color_image,
    read_depth_png,
)


@dataclass
class RGBDSequence:
    """One continuous RGB-D video.

    Attributes:
        root: the sequence folder.
        name: its path relative to the discovery root (the root's name when it is the root).
        layout: the name of its layout (:func:`~byoc_cli.io.rgbd.registry.registered_layouts`).
        frames: usable frames, in time order.
        K: ``(3, 3)`` float64 intrinsics of the DEPTH camera.
        depth_scale: raw depth units per metre.
        depth_shape: ``(H, W)`` of the depth images (from the intrinsics file or the first
            readable frame), or None when unknown; frames of another size raise
            :class:`FrameError` when read.
        skipped: frames or listed images dropped at discovery, with the reason.
        intrinsics_source: where ``K`` came from (a file, ``"freiburgN (published)"`` or
            ``"override"``).
    """

    root: Path
    name: str
    layout: str
    frames: list[RGBDFrame]
    K: np.ndarray
    depth_scale: float
    depth_shape: tuple[int, int] | None = None
    skipped: list[SkippedFrame] = field(default_factory=list)
    intrinsics_source: str = ""

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def num_skipped(self) -> int:
        """Number of frames (or listed images) dropped at discovery."""
        return len(self.skipped)

    @property
    def has_color(self) -> bool:
        """True when every frame has a colour image (and there is at least one frame)."""
        return bool(self.frames) and all(f.color_path is not None for f in self.frames)

    @property
    def has_poses(self) -> bool:
        """True when every frame has a valid pose (and there is at least one frame)."""
        return bool(self.frames) and all(f.pose is not None for f in self.frames)

    def pose(self, i: int) -> np.ndarray | None:
        """Camera-to-world pose ``T_world_cam`` of frame ``i`` (a copy), or None.

        Args:
            i: position in :attr:`frames`.

        Returns:
            ``(4, 4)`` float64, or None when the frame has no valid pose.
        """
        pose = self.frames[i].pose
        return None if pose is None else pose.copy()

    def read_depth(self, i: int) -> np.ndarray:
        """Read the depth of frame ``i`` in metres.

        Args:
            i: position in :attr:`frames`.

        Returns:
            ``(H, W)`` float32 metres; 0 where depth is missing (raw 0 or 65535, non-finite
            or negative values of float images).

        Raises:
            FrameError: the file is gone, corrupt, not a depth image or not ``depth_shape``.
        """
        path = self.frames[i].depth_path
        depth = read_depth_png(path, self.depth_scale, frame=i)
        if self.depth_shape is not None and depth.shape != tuple(self.depth_shape):
            raise FrameError(
                path,
                f"depth image is {depth.shape[1]}x{depth.shape[0]}, the sequence's is "
                f"{self.depth_shape[1]}x{self.depth_shape[0]}",
                frame=i,
            )
        return depth

    def read_color(self, i: int) -> np.ndarray:
        """Read the colour of frame ``i`` at the depth resolution.

        Colour of another size (ScanNet: 1296x968 colour, 640x480 depth) is resized to the
        depth size with bilinear filtering.

        Args:
            i: position in :attr:`frames`.

        Returns:
            ``(H, W, 3)`` uint8 RGB with ``(H, W)`` = :attr:`depth_shape`.

        Raises:
            FrameError: the frame has no colour, or its file is gone or corrupt.
        """
        frame = self.frames[i]
        if frame.color_path is None:
            raise FrameError(frame.depth_path, "frame has no colour image", frame=i)
        shape = self.depth_shape
        if shape is None:
            shape = image_shape(frame.depth_path, frame=i)
        return read_color_image(frame.color_path, shape, frame=i)
