"""3DMatch RGB-D layout, also 7-Scenes and SUN3D.

``camera-intrinsics.txt`` (3x3) in the sequence folder or an ancestor,
``seq-XX/frame-XXXXXX.{depth.png, color.png|color.jpg, pose.txt}``; depth in millimetres
(0 and 65535 invalid); ``pose.txt`` a 4x4 camera-to-world matrix; one sequence per folder of
frames, and a scene folder may hold several (``seq-01/``, ``seq-02/``, ...).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from byoc_cli.io.rgbd.files import find_up, layout_intrinsics, read_pose
from byoc_cli.io.rgbd.frames import RGBDFrame, SkippedFrame
from byoc_cli.io.rgbd.layout import Layout, ScanOptions

_FRAME = re.compile(r"^frame-(\d+)\.depth\.png$")


def _frames(
    folder: Path, names: list[str], options: ScanOptions
) -> tuple[list[RGBDFrame], list[SkippedFrame]]:
    """``frame-XXXXXX.depth.png`` in number order, with colour and pose when present."""
    present = set(names)
    numbered = []
    for name in names:
        m = _FRAME.match(name)
        if m:
            numbered.append((int(m.group(1)), name[: -len(".depth.png")]))
    numbered.sort()
    frames = []
    for number, stem in numbered:
        color = None
        for ext in (".color.png", ".color.jpg", ".color.jpeg"):
            if stem + ext in present:
                color = folder / (stem + ext)
                break
        pose_name = stem + ".pose.txt"
        pose = (
            read_pose(folder / pose_name) if options.read_poses and pose_name in present else None
        )
        frames.append(RGBDFrame(number, folder / (stem + ".depth.png"), color, pose, None))
    return frames, []


def _detect(folder: Path, names: list[str]) -> bool:
    return any(_FRAME.match(n) for n in names)


def _intrinsics(folder: Path, root: Path) -> tuple[np.ndarray, tuple[int, int] | None, str]:
    path = find_up(folder, root, ["camera-intrinsics.txt"], parent=True)
    what = "camera-intrinsics.txt (in the sequence folder or its parent)"
    return layout_intrinsics(folder, "3dmatch", path, what)


LAYOUT = Layout(
    name="3dmatch",
    description="3DMatch seq-XX/",
    depth_scale=1000.0,
    detect=_detect,
    frames=_frames,
    intrinsics=_intrinsics,
    search_inside=True,
)
