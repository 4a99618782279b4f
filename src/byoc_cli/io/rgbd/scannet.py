"""ScanNet export layout.

``depth/N.png`` (mm), ``color/N.jpg``, ``pose/N.txt`` (4x4 camera-to-world),
``intrinsic/intrinsic_depth.txt`` (4x4). The DEPTH intrinsics are used, never the colour ones
(the authors' implementation used the colour ones, about 0.5 % off: docs/training.md);
colour, shot at another resolution, is resized to the depth resolution when read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from byoc_cli.io.rgbd.files import (
    images_by_stem,
    layout_intrinsics,
    list_dir,
    natural_key,
    read_pose,
)
from byoc_cli.io.rgbd.frames import RGBDFrame, SkippedFrame
from byoc_cli.io.rgbd.layout import Layout, ScanOptions


def _frames(
    folder: Path, names: list[str], options: ScanOptions
) -> tuple[list[RGBDFrame], list[SkippedFrame]]:
    """``depth/N.png`` in number order, with ``color/N.*`` and ``pose/N.txt`` when present."""
    depth = {s: p for s, p in images_by_stem(folder / "depth").items() if p.suffix == ".png"}
    color = images_by_stem(folder / "color")
    poses = set(list_dir(folder / "pose"))
    frames = []
    for stem in sorted(depth, key=natural_key):
        number = int(stem) if stem.isdigit() else len(frames)
        has_pose = options.read_poses and f"{stem}.txt" in poses
        pose = read_pose(folder / "pose" / f"{stem}.txt") if has_pose else None
        frames.append(RGBDFrame(number, depth[stem], color.get(stem), pose, None))
    return frames, []


def _detect(folder: Path, names: list[str]) -> bool:
    if not ("depth" in names and (folder / "depth").is_dir()):
        return False
    return ("intrinsic" in names and (folder / "intrinsic").is_dir()) or (
        "pose" in names and (folder / "pose").is_dir()
    )


def _intrinsics(folder: Path, root: Path) -> tuple[np.ndarray, tuple[int, int] | None, str]:
    path = folder / "intrinsic" / "intrinsic_depth.txt"
    what = "intrinsic/intrinsic_depth.txt (the colour intrinsics are not used for depth)"
    return layout_intrinsics(folder, "scannet", path if path.is_file() else None, what)


LAYOUT = Layout(
    name="scannet",
    description="ScanNet color/depth/pose/",
    depth_scale=1000.0,
    detect=_detect,
    frames=_frames,
    intrinsics=_intrinsics,
)
