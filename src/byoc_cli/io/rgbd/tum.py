"""TUM RGB-D layout.

``rgb.txt`` and ``depth.txt`` (``timestamp path`` lines, ``#`` comments), colour associated to
depth by nearest timestamp (unique, within ``max_time_difference``, 0.02 s by default, like
TUM's ``associate.py``; ``rgb.txt`` is optional: depth-only sequences have none); depth
1/5000 m; intrinsics from ``intrinsics.json`` (Open3D ``PinholeCameraIntrinsic``,
``intrinsic_matrix`` column-major), else the published freiburg1/2/3 values when a folder name
from the sequence up to the root says ``freiburg1``/``fr1`` etc.; optional ``groundtruth.txt``
(``timestamp tx ty tz qx qy qz qw``, camera-to-world, the nearest stamp within
``pose_time_tolerance``).
"""

from __future__ import annotations

import array
import io
import math
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from byoc_cli.errors import DatasetError, ShapeError
from byoc_cli.io.rgbd.files import names_up_to, read_K, read_text
from byoc_cli.io.rgbd.frames import RGBDFrame, SkippedFrame
from byoc_cli.io.rgbd.layout import Layout, ScanOptions
from byoc_cli.io.trajectory import quaternion_to_matrix

#: Published TUM RGB-D intrinsics ``(fx, fy, cx, cy)`` per Kinect (freiburg1/2/3).
TUM_INTRINSICS = {
    1: (517.3, 516.5, 318.6, 255.3),
    2: (520.9, 521.0, 325.1, 249.7),
    3: (535.4, 539.2, 320.1, 247.6),
}

_FREIBURG = re.compile(r"(?<![a-z0-9])(?:freiburg|fr)_?([123])(?![0-9])", re.IGNORECASE)


def _tum_lines(path: Path, skipped: list[SkippedFrame]) -> Iterator[tuple[float, list[str]]]:
    """``(stamp, values)`` of the ``timestamp value...`` lines (``#`` comments), in file order,
    one at a time (a file of millions of short lines never exists as a list of lines)."""
    for number, line in enumerate(io.StringIO(read_text(path), newline=None), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").replace("\t", " ").split()
        try:
            stamp = float(fields[0])
        except ValueError:
            stamp = math.nan
        if len(fields) < 2 or not math.isfinite(stamp):
            skipped.append(SkippedFrame(f"{path.name}:{number}", "unparseable line"))
            continue
        yield stamp, fields[1:]


def _read_tum_list(path: Path, skipped: list[SkippedFrame]) -> list[tuple[float, list[str]]]:
    """``timestamp value...`` lines (``#`` comments) -> ``[(stamp, values)]`` sorted by stamp."""
    return sorted(_tum_lines(path, skipped), key=lambda e: e[0])


def _read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``groundtruth.txt`` -> ``(stamps (N,), values (N, 7))`` float64 sorted by stamp (a value
    that is not a number is NaN; lines with fewer than 7 values are dropped). Kept as two
    arrays, 64 bytes a line: a pose is made only for the frames that use it."""
    stamps, values = array.array("d"), array.array("d")
    for stamp, fields in _tum_lines(path, []):  # bad ground-truth lines only cost poses
        if len(fields) < 7:
            continue
        stamps.append(stamp)
        for text in fields[:7]:
            try:
                values.append(float(text))
            except ValueError:
                values.append(math.nan)
    order = np.argsort(np.frombuffer(stamps, dtype=np.float64), kind="stable")
    table = np.frombuffer(values, dtype=np.float64).reshape(-1, 7)
    return np.frombuffer(stamps, dtype=np.float64)[order], table[order]


def _associate(a: np.ndarray, b: np.ndarray, max_difference: float) -> dict[int, int]:
    """TUM ``associate.py``: unique pairs ``a[i] <-> b[j]``, closest first, within the limit.

    Returns:
        ``{i: j}``.
    """
    if len(a) == 0 or len(b) == 0:
        return {}
    order = np.argsort(b, kind="stable")
    b_sorted = b[order]
    lo = np.searchsorted(b_sorted, a - max_difference, side="left")
    hi = np.searchsorted(b_sorted, a + max_difference, side="right")
    candidates = []
    for i in range(len(a)):
        for k in range(lo[i], hi[i]):
            diff = abs(float(a[i]) - float(b_sorted[k]))
            if diff < max_difference:
                candidates.append((diff, i, int(order[k])))
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    matches = {}
    for _diff, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            matches[i] = j
    return matches


def _nearest(stamps: np.ndarray, t: float, tolerance: float) -> int | None:
    if len(stamps) == 0:
        return None
    k = int(np.searchsorted(stamps, t))
    best = None
    for c in (k - 1, k):
        if 0 <= c < len(stamps) and abs(stamps[c] - t) <= tolerance:
            if best is None or abs(stamps[c] - t) < abs(stamps[best] - t):
                best = c
    return best


def _quaternion_pose(values: list[float]) -> np.ndarray | None:
    """``tx ty tz qx qy qz qw`` -> 4x4 ``T_world_cam``, or None when invalid."""
    t = np.array(values[:3], dtype=np.float64)
    if not np.all(np.isfinite(t)):
        return None
    try:
        R = quaternion_to_matrix(np.array(values[3:7], dtype=np.float64))
    except ShapeError:
        return None
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _tum_frames(
    folder: Path, names: list[str], options: ScanOptions
) -> tuple[list[RGBDFrame], list[SkippedFrame]]:
    """Depth frames of ``depth.txt`` with the nearest colour of ``rgb.txt`` and pose."""
    max_time_difference = options.max_time_difference
    pose_tolerance = options.pose_time_tolerance
    skipped: list[SkippedFrame] = []
    depth_list = _read_tum_list(folder / "depth.txt", skipped)
    rgb_list = _read_tum_list(folder / "rgb.txt", skipped) if (folder / "rgb.txt").is_file() else []
    depth_t = np.array([e[0] for e in depth_list], dtype=np.float64)
    rgb_t = np.array([e[0] for e in rgb_list], dtype=np.float64)
    match = _associate(depth_t, rgb_t, max_time_difference)
    matched_rgb = set(match.values())
    for j, (stamp, values) in enumerate(rgb_list):
        if j not in matched_rgb:
            skipped.append(
                SkippedFrame(
                    values[0],
                    f"colour at {stamp:.6f} s has no depth within {max_time_difference:g} s",
                )
            )

    gt_t, gt_values = np.zeros(0), np.zeros((0, 7))
    gt_path = folder / "groundtruth.txt"
    if options.read_poses and gt_path.is_file():
        gt_t, gt_values = _read_groundtruth(gt_path)

    frames = []
    for i, (stamp, values) in enumerate(depth_list):
        depth_path = folder / values[0]
        if not depth_path.is_file():
            skipped.append(SkippedFrame(values[0], "depth file not found"))
            continue
        color_path = None
        if i in match:
            candidate = folder / rgb_list[match[i]][1][0]
            if candidate.is_file():
                color_path = candidate
            else:
                skipped.append(SkippedFrame(rgb_list[match[i]][1][0], "colour file not found"))
        k = _nearest(gt_t, stamp, pose_tolerance)
        pose = _quaternion_pose(list(gt_values[k])) if k is not None else None
        frames.append(RGBDFrame(i, depth_path, color_path, pose, stamp))
    return frames, skipped


def _freiburg_K(folder: Path, root: Path) -> tuple[np.ndarray, str] | None:
    for part in names_up_to(folder, root):
        m = _FREIBURG.search(part)
        if m:
            fx, fy, cx, cy = TUM_INTRINSICS[int(m.group(1))]
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            return K, f"freiburg{m.group(1)} (published)"
    return None


def _detect(folder: Path, names: list[str]) -> bool:
    return "depth.txt" in names and (folder / "depth.txt").is_file()


def _intrinsics(folder: Path, root: Path) -> tuple[np.ndarray, tuple[int, int] | None, str]:
    path = folder / "intrinsics.json"
    if path.is_file():
        K, shape = read_K(path)
        return K, shape, str(path)
    named = _freiburg_K(folder, root)
    if named is not None:
        return named[0], None, named[1]
    raise DatasetError(
        folder,
        "TUM sequence without intrinsics: no intrinsics.json and no freiburg1/2/3 (fr1/2/3) "
        "in the folder names; give the intrinsics explicitly",
    )


LAYOUT = Layout(
    name="tum",
    description="TUM rgb.txt/depth.txt",
    depth_scale=5000.0,
    detect=_detect,
    frames=_tum_frames,
    intrinsics=_intrinsics,
)
