"""RGB-D video readers, frame pairs and the 128x128 preprocessing of the paper's
variants (docs/training.md).

One module per idea:

* ``frames.py``: :class:`RGBDFrame`, :class:`SkippedFrame`, :class:`FrameError`, image decoding;
* ``sequence.py``: :class:`RGBDSequence` (frames, intrinsics, depth scale, frame reads);
* ``layout.py``, ``registry.py``: what a layout provides, and the registered layouts;
* ``tum.py``, ``threedmatch.py`` (also 7-Scenes, SUN3D), ``scannet.py``, ``redwood.py``
  (Open3D / Redwood): one module per dataset layout, each documenting its files;
* ``files.py``: text, intrinsics and pose files shared by the layouts;
* ``discovery.py``: :func:`discover_sequences`, recursive, through the registry;
* ``pairs.py``: :func:`make_pairs`;
* ``preprocess.py``, ``backproject.py``: :func:`preprocess_frame`, :func:`backproject`.

Colour is optional everywhere: a sequence without colour is usable for depth-only training.
Depth is the reference: a frame is a depth image, its colour and pose are attached when found.
Poses are camera-to-world ``T_world_cam`` (4x4, float64); an invalid pose (non-finite, not
rigid) leaves the frame without a pose.

Missing and corrupt frames are never fatal:

* at discovery, frames whose listed depth file (or, with ``require_color``, colour file) does
  not exist are dropped and recorded in :attr:`RGBDSequence.skipped`; with ``verify=True``
  every image is also decoded and checked (format, size) and bad frames dropped the same way;
* at read time (``verify=False``, the default, to keep discovery cheap), a frame whose file
  vanished, is corrupt, has the wrong pixel format or size raises :class:`FrameError`, which
  data loaders catch, count and replace by another sample.

Geometry: OpenCV camera axes (x right, y down, z forward); a pixel ``(u, v)`` is column ``u``,
row ``v``, back-projected through its centre ``(u + 0.5, v + 0.5)``.

Depends on numpy, pillow and :mod:`byoc_cli.errors` only.
"""

from byoc_cli.io.rgbd.backproject import BackProjection, backproject
from byoc_cli.io.rgbd.discovery import discover_sequences
from byoc_cli.io.rgbd.frames import FrameError, RGBDFrame, SkippedFrame
from byoc_cli.io.rgbd.layout import Layout, ScanOptions
from byoc_cli.io.rgbd.pairs import make_pairs
from byoc_cli.io.rgbd.preprocess import PreprocessedFrame, preprocess_frame
from byoc_cli.io.rgbd.registry import (
    DEFAULT_DEPTH_SCALE,
    LAYOUTS,
    register_layout,
    registered_layouts,
    unregister_layout,
)
from byoc_cli.io.rgbd.sequence import RGBDSequence
from byoc_cli.io.rgbd.tum import TUM_INTRINSICS

__all__ = [
    "DEFAULT_DEPTH_SCALE",
    "LAYOUTS",
    "TUM_INTRINSICS",
    "BackProjection",
    "FrameError",
    "Layout",
    "PreprocessedFrame",
    "RGBDFrame",
    "RGBDSequence",
    "ScanOptions",
    "SkippedFrame",
    "backproject",
    "discover_sequences",
    "make_pairs",
    "preprocess_frame",
    "register_layout",
    "registered_layouts",
    "unregister_layout",
]
