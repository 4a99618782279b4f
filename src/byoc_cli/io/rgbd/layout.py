"""What a dataset layout provides to discovery: :class:`Layout`, one per layout module.

A layout module (``tum.py``, ``threedmatch.py``, ...) defines ``LAYOUT = Layout(...)`` with
three functions, and :mod:`byoc_cli.io.rgbd.registry` lists it. Discovery walks the folders
under a root, asks each registered layout in turn whether a folder is one of its sequences
(:attr:`Layout.detect`), then lists its frames and reads its intrinsics through the layout.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from byoc_cli.io.rgbd.frames import RGBDFrame, SkippedFrame


class ScanOptions(NamedTuple):
    """Discovery settings a layout's frame listing may use.

    Attributes:
        max_time_difference: colour-depth association limit (timestamped layouts), seconds.
        pose_time_tolerance: ground-truth association limit (timestamped layouts), seconds.
        read_poses: False: never open a pose or ground-truth file (every pose is None).
    """

    max_time_difference: float = 0.02
    pose_time_tolerance: float = 0.02
    read_poses: bool = True


#: ``frames(folder, entry names, options) -> (frames in time order, skipped)``.
FramesFn = Callable[[Path, list[str], ScanOptions], tuple[list[RGBDFrame], list[SkippedFrame]]]
#: ``intrinsics(folder, root) -> (K (3, 3) float64, (H, W) or None, source)``.
IntrinsicsFn = Callable[[Path, Path], tuple[np.ndarray, tuple[int, int] | None, str]]


@dataclass(frozen=True)
class Layout:
    """One dataset layout.

    Attributes:
        name: the layout's name, as in :attr:`RGBDSequence.layout`.
        description: what discovery looks for, for the "nothing found" message
            (e.g. ``"TUM rgb.txt/depth.txt"``).
        depth_scale: raw depth units per metre of its depth images.
        detect: ``detect(folder, entry names) -> bool``: is ``folder`` a sequence of this
            layout? Called with the folder's sorted entry names; must be cheap.
        frames: lists the frames of a detected sequence folder: depth is the reference,
            colour and pose are attached when found; frames whose depth file is missing are
            returned in ``skipped``, never raised.
        intrinsics: ``(K, (H, W) or None, source)`` of the DEPTH camera of a sequence folder
            (``root`` is the discovery root, the highest folder to search for a shared
            intrinsics file); raises :class:`~byoc_cli.errors.DatasetError` when there are
            none.
        search_inside: keep looking for sequences in the sub-folders of a sequence folder of
            this layout (3DMatch scene folders hold ``seq-XX/``); otherwise its sub-folders
            (``rgb/``, ``depth/``, ...) are its own.
    """

    name: str
    description: str
    depth_scale: float
    detect: Callable[[Path, list[str]], bool]
    frames: FramesFn
    intrinsics: IntrinsicsFn
    search_inside: bool = False
