"""Open3D / Redwood layout.

``depth/`` and ``color/`` (or ``image/``, ``rgb/``) images, matched by file stem or else by
sorted order (colour is optional: depth-only recordings have none), ``intrinsic.json`` or
``camera_intrinsic.json`` in the sequence folder or an ancestor; depth in millimetres; no
poses. It is the catch-all "folder with a ``depth/``" layout: it is registered last.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from byoc_cli.io.rgbd.files import find_up, images_by_stem, layout_intrinsics, natural_key
from byoc_cli.io.rgbd.frames import RGBDFrame, SkippedFrame
from byoc_cli.io.rgbd.layout import Layout, ScanOptions

_COLOR_DIRS = ("color", "image", "rgb")
_INTRINSICS_FILES = ("intrinsic.json", "camera_intrinsic.json")


def _frames(
    folder: Path, names: list[str], options: ScanOptions
) -> tuple[list[RGBDFrame], list[SkippedFrame]]:
    """``depth/*.png`` in natural order, colour matched by stem or else by sorted order."""
    depth = {s: p for s, p in images_by_stem(folder / "depth").items() if p.suffix == ".png"}
    color: dict[str, Path] = {}
    for name in _COLOR_DIRS:
        if (folder / name).is_dir():
            color = images_by_stem(folder / name)
            if color:
                break
    depth_stems = sorted(depth, key=natural_key)
    color_stems = sorted(color, key=natural_key)
    if color and set(depth_stems) != set(color_stems) and len(depth_stems) == len(color_stems):
        pairing = dict(zip(depth_stems, color_stems, strict=True))  # by sorted order
    else:
        pairing = {s: s for s in depth_stems if s in color}  # by stem
    frames = [
        RGBDFrame(i, depth[s], color[pairing[s]] if s in pairing else None, None, None)
        for i, s in enumerate(depth_stems)
    ]
    skipped = [
        SkippedFrame(str(color[s]), "colour image without a depth image")
        for s in sorted(set(color_stems) - set(pairing.values()), key=natural_key)
    ]
    return frames, skipped


def _detect(folder: Path, names: list[str]) -> bool:
    return "depth" in names and (folder / "depth").is_dir()


def _intrinsics(folder: Path, root: Path) -> tuple[np.ndarray, tuple[int, int] | None, str]:
    path = find_up(folder, root, _INTRINSICS_FILES, parent=False)
    return layout_intrinsics(folder, "redwood", path, "intrinsic.json or camera_intrinsic.json")


LAYOUT = Layout(
    name="redwood",
    description="Redwood depth/",
    depth_scale=1000.0,
    detect=_detect,
    frames=_frames,
    intrinsics=_intrinsics,
)
