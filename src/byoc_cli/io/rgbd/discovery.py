"""Finding RGB-D sequences under a folder: :func:`discover_sequences`.

Folders are walked recursively; each is offered to the registered layouts
(:mod:`byoc_cli.io.rgbd.registry`) and the first that recognises it lists its frames and
reads its intrinsics. Missing and corrupt frames are never fatal: frames whose listed depth
file (or, with ``require_color``, colour file) does not exist are dropped and recorded in
:attr:`RGBDSequence.skipped`; with ``verify=True`` every image is also decoded and checked
(format, size) and bad frames dropped the same way; otherwise a bad frame raises
:class:`FrameError` when it is read.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

from byoc_cli.errors import DatasetError
from byoc_cli.io.rgbd.files import list_dir, override_K
from byoc_cli.io.rgbd.frames import FrameError, RGBDFrame, SkippedFrame, image_shape
from byoc_cli.io.rgbd.layout import Layout, ScanOptions
from byoc_cli.io.rgbd.registry import detect_layout, not_found_message
from byoc_cli.io.rgbd.sequence import RGBDSequence


def _walk(root: Path) -> list[tuple[Path, Layout, list[str]]]:
    """Sequence folders under ``root``: ``[(folder, layout, entry names)]``, sorted."""
    found = []
    seen: set[str] = set()

    def visit(folder: Path) -> None:
        real = os.path.realpath(folder)
        if real in seen:
            return
        seen.add(real)
        names = list_dir(folder)
        layout = detect_layout(folder, names)
        if layout is not None:
            found.append((folder, layout, names))
            if not layout.search_inside:
                return  # the sequence's own sub-folders (rgb/, depth/, ...) hold no sequence
        for name in names:
            child = folder / name
            if not name.startswith(".") and child.is_dir():
                visit(child)

    visit(root)
    return found


def _probe_shape(frames: list[RGBDFrame], tries: int = 5) -> tuple[int, int] | None:
    for frame in frames[:tries]:
        try:
            return image_shape(frame.depth_path)
        except FrameError:
            continue
    return None


def _verify(seq: RGBDSequence, check_color: bool) -> RGBDSequence:
    """Decode every frame; drop (and record) those that cannot be read."""
    frames, skipped = [], list(seq.skipped)
    for i, frame in enumerate(seq.frames):
        try:
            seq.read_depth(i)
            if check_color and frame.color_path is not None:
                seq.read_color(i)
        except FrameError as exc:
            skipped.append(SkippedFrame(exc.path, exc.problem))
            continue
        frames.append(frame)
    return replace(seq, frames=frames, skipped=skipped)


def discover_sequences(
    root: str | os.PathLike[str],
    intrinsics: Any = None,
    depth_scale: float | None = None,
    require_color: bool = False,
    *,
    require_poses: bool = False,
    verify: bool = False,
    **scan: Any,
) -> list[RGBDSequence]:
    """Find every RGB-D sequence under ``root`` (recursively) and list its usable frames.

    Sequences are sorted by their path relative to ``root``; frames are in time order. A
    folder recognised as a sequence is not searched further, except 3DMatch scene folders
    (their ``seq-XX/`` are sequences). Hidden folders are ignored.

    Frames are dropped (and recorded in :attr:`RGBDSequence.skipped`) when the depth file is
    missing, when ``require_color`` and the colour is missing, when ``require_poses`` and the
    pose is missing or invalid, and with ``verify`` when an image cannot be decoded or has the
    wrong size. A sequence left without frames is dropped with a warning.

    Args:
        root: a sequence folder or a folder of sequences.
        intrinsics: explicit DEPTH intrinsics for every sequence, overriding the files found:
            an intrinsics file (Open3D JSON or 3x3/4x4 text), a ``(3, 3)`` matrix, or an
            object with a ``K`` attribute. None: per sequence, from its layout's file (TUM:
            ``intrinsics.json``, else the published freiburg1/2/3 values by folder name).
        depth_scale: raw depth units per metre for every sequence; None: the layout's
            (:attr:`Layout.depth_scale`: 5000 TUM, 1000 the others).
        require_color: keep only frames with colour; sequences without colour are dropped.
        require_poses: keep only frames with a valid pose.
        verify: decode every image now (slow) instead of failing at read time.
        scan: the fields of :class:`~byoc_cli.io.rgbd.layout.ScanOptions`:
            ``max_time_difference`` (TUM rgb-depth association limit, seconds),
            ``pose_time_tolerance`` (TUM ground-truth association limit, seconds) and
            ``read_poses`` (False: never open a pose or ground-truth file, training data;
            every frame's pose is None; incompatible with ``require_poses``).

    Returns:
        The sequences (never empty).

    Raises:
        DatasetError: ``root`` is missing or not a folder; no sequence (or none with colour,
            with poses, or with a frame) is found; a sequence has no intrinsics, unreadable
            intrinsics, or intrinsics for another image size; ``depth.txt`` is unreadable.
        InputError: the ``intrinsics`` file cannot be used.
        ShapeError: ``intrinsics`` is an array that is not 3x3.
        ValueError: ``depth_scale`` or a tolerance is not a positive number.
        TypeError: an unknown keyword.
    """
    options = ScanOptions(**scan)
    root = Path(root)
    if not root.exists():
        raise DatasetError(root, "folder does not exist")
    if not root.is_dir():
        raise DatasetError(root, "not a folder")
    if depth_scale is not None and not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale must be positive (raw units per metre), got {depth_scale}")
    for label, value in (
        ("max_time_difference", options.max_time_difference),
        ("pose_time_tolerance", options.pose_time_tolerance),
    ):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{label} must be a positive number of seconds, got {value}")
    override = override_K(intrinsics) if intrinsics is not None else None
    if require_poses and not options.read_poses:
        raise ValueError("require_poses needs read_poses")

    sequences = []
    dropped = {"color": 0, "poses": 0, "frames": 0}
    for folder, layout, names in _walk(root):
        frames, skipped = layout.frames(folder, names, options)
        if override is not None:
            K, shape, source = override
        else:
            K, shape, source = layout.intrinsics(folder, root)
        rel = folder.relative_to(root).as_posix()
        seq = RGBDSequence(
            root=folder,
            name=root.name if rel == "." else rel,
            layout=layout.name,
            frames=frames,
            K=K,
            depth_scale=float(depth_scale or layout.depth_scale),
            depth_shape=None,
            skipped=skipped,
            intrinsics_source=source,
        )
        if require_color:
            if not any(f.color_path is not None for f in seq.frames):
                dropped["color"] += 1
                continue
            seq.skipped += [
                SkippedFrame(str(f.depth_path), "no colour")
                for f in seq.frames
                if f.color_path is None
            ]
            seq.frames = [f for f in seq.frames if f.color_path is not None]
        if require_poses:
            if not any(f.pose is not None for f in seq.frames):
                dropped["poses"] += 1
                continue
            seq.skipped += [
                SkippedFrame(str(f.depth_path), "no valid pose")
                for f in seq.frames
                if f.pose is None
            ]
            seq.frames = [f for f in seq.frames if f.pose is not None]
        probed = _probe_shape(seq.frames)
        if shape is not None and probed is not None and shape != probed:
            raise DatasetError(
                source,
                f"intrinsics are for {shape[1]}x{shape[0]} images but the depth images of "
                f"{folder} are {probed[1]}x{probed[0]}",
            )
        seq.depth_shape = shape or probed
        if verify:
            seq = _verify(seq, check_color=require_color)
        if not seq.frames:
            dropped["frames"] += 1
            warnings.warn(f"{folder}: RGB-D sequence without a usable frame, ignored", stacklevel=2)
            continue
        sequences.append(seq)

    if not sequences:
        if dropped["color"]:
            raise DatasetError(
                root,
                f"no RGB-D sequence with colour images found "
                f"({dropped['color']} depth-only sequence(s))",
            )
        if dropped["poses"]:
            raise DatasetError(
                root, f"no RGB-D sequence with poses found ({dropped['poses']} sequence(s) without)"
            )
        if dropped["frames"]:
            raise DatasetError(
                root, f"no usable frame in the {dropped['frames']} RGB-D sequence(s) found"
            )
        raise DatasetError(root, not_found_message())
    return sequences
