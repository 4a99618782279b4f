"""RGB-D video readers, frame pairs and the 128x128 preprocessing of method.md section 1.

Layouts, found recursively under a root (one sequence or many):

``tum``
    TUM RGB-D: ``rgb.txt`` and ``depth.txt`` (``timestamp path`` lines, ``#`` comments),
    colour associated to depth by nearest timestamp (unique, within ``max_time_difference``,
    0.02 s by default, like TUM's ``associate.py``); depth 1/5000 m; intrinsics from
    ``intrinsics.json`` (Open3D ``PinholeCameraIntrinsic``, ``intrinsic_matrix``
    column-major), else the published freiburg1/2/3 values when a folder name from the
    sequence up to the root says ``freiburg1``/``fr1`` etc.; optional ``groundtruth.txt``
    (``timestamp tx ty tz qx qy qz qw``, camera-to-world, the nearest stamp within
    ``pose_time_tolerance``).
``3dmatch``
    3DMatch RGB-D, 7-Scenes, SUN3D: ``camera-intrinsics.txt`` (3x3) in the sequence folder or
    an ancestor, ``seq-XX/frame-XXXXXX.{depth.png, color.png|color.jpg, pose.txt}``; depth in
    millimetres (0 and 65535 invalid); one sequence per folder of frames.
``scannet``
    ScanNet export: ``depth/N.png`` (mm), ``color/N.jpg``, ``pose/N.txt``,
    ``intrinsic/intrinsic_depth.txt`` (4x4). The DEPTH intrinsics are used, never the colour
    ones (method.md 10.5); colour, shot at another resolution, is resized to the depth
    resolution when read.
``redwood``
    Open3D / Redwood: ``depth/`` and ``color/`` (or ``image/``, ``rgb/``) images, matched by
    file stem or else by sorted order, ``intrinsic.json`` or ``camera_intrinsic.json`` (in the
    sequence folder or an ancestor); depth in millimetres.

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

from __future__ import annotations

import json
import math
import os
import re
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from byoc_cli.errors import DatasetError, InputError, ShapeError

__all__ = [
    "DEFAULT_DEPTH_SCALE",
    "LAYOUTS",
    "TUM_INTRINSICS",
    "FrameError",
    "PreprocessedFrame",
    "RGBDFrame",
    "RGBDSequence",
    "SkippedFrame",
    "backproject",
    "discover_sequences",
    "make_pairs",
    "preprocess_frame",
]

#: Layout names, as in :attr:`RGBDSequence.layout`.
LAYOUTS = ("tum", "3dmatch", "scannet", "redwood")

#: Raw depth units per metre of each layout (overridable with ``depth_scale``).
DEFAULT_DEPTH_SCALE = {"tum": 5000.0, "3dmatch": 1000.0, "scannet": 1000.0, "redwood": 1000.0}

#: Published TUM RGB-D intrinsics ``(fx, fy, cx, cy)`` per Kinect (freiburg1/2/3).
TUM_INTRINSICS = {
    1: (517.3, 516.5, 318.6, 255.3),
    2: (520.9, 521.0, 325.1, 249.7),
    3: (535.4, 539.2, 320.1, 247.6),
}

#: Raw value that marks a missing measurement in 16-bit depth images (raw 7-Scenes).
_INVALID_DEPTH_16 = 65535
_DEPTH_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I", "F")
_COLOR_DIRS = ("color", "image", "rgb")
_IMAGE_EXTS = (".png", ".jpg", ".jpeg")
_REDWOOD_INTRINSICS = ("intrinsic.json", "camera_intrinsic.json")
_FREIBURG = re.compile(r"(?<![a-z0-9])(?:freiburg|fr)_?([123])(?![0-9])", re.IGNORECASE)
_FRAME_3DMATCH = re.compile(r"^frame-(\d+)\.depth\.png$")
_NOT_FOUND = (
    "no RGB-D sequence found (looked for TUM rgb.txt/depth.txt, 3DMatch seq-XX/, "
    "ScanNet color/depth/pose/, Redwood depth/)"
)


# ================================================================== types


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


class BackProjection(NamedTuple):
    """Output of :func:`backproject`.

    Attributes:
        points: ``(N, 3)`` float32 camera-frame points in metres.
        pixel_index: ``(N,)`` int64 row-major pixel of each point, ``v * W + u``.
    """

    points: np.ndarray
    pixel_index: np.ndarray


@dataclass
class RGBDSequence:
    """One continuous RGB-D video.

    Attributes:
        root: the sequence folder.
        name: its path relative to the discovery root (the root's name when it is the root).
        layout: one of :data:`LAYOUTS`.
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
        depth = _read_depth_png(path, self.depth_scale, frame=i)
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
            shape = _image_shape(frame.depth_path, frame=i)
        return _read_color_image(frame.color_path, shape, frame=i)


# ================================================================== private reading


def _open_image(path: Path, frame: int | None):
    """Open an image with pillow (lazily), mapping every failure to :class:`FrameError`."""
    from PIL import Image, UnidentifiedImageError

    try:
        return Image.open(path)
    except FileNotFoundError as exc:
        raise FrameError(path, "file not found", frame) from exc
    except UnidentifiedImageError as exc:
        raise FrameError(path, "not an image file (pillow cannot identify it)", frame) from exc
    except (OSError, SyntaxError, ValueError) as exc:
        raise FrameError(path, f"cannot open image ({exc})", frame) from exc


def _image_shape(path: Path, frame: int | None = None) -> tuple[int, int]:
    """``(H, W)`` of an image from its header."""
    with _open_image(path, frame) as image:
        width, height = image.size
    return int(height), int(width)


def _read_depth_png(path: Path, depth_scale: float, frame: int | None = None) -> np.ndarray:
    """16-bit (or 32-bit int / float) depth image -> ``(H, W)`` float32 metres, 0 = invalid."""
    with _open_image(path, frame) as image:
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
        invalid = (raw <= 0) | (raw == _INVALID_DEPTH_16)
    depth[invalid] = 0.0
    return depth


def _read_color_image(path: Path, shape: tuple[int, int], frame: int | None = None) -> np.ndarray:
    """Colour image -> ``(H, W, 3)`` uint8 RGB at ``shape`` (bilinear resize when needed)."""
    from PIL import Image

    height, width = shape
    with _open_image(path, frame) as image:
        try:
            rgb = image.convert("RGB")
            if rgb.size != (width, height):
                rgb = rgb.resize((width, height), Image.Resampling.BILINEAR)
            array = np.asarray(rgb, dtype=np.uint8)
        except (OSError, SyntaxError, ValueError) as exc:
            raise FrameError(path, f"truncated or corrupt image ({exc})", frame) from exc
    return np.ascontiguousarray(array)


def _read_text(path: Path, error: type[InputError] = DatasetError) -> str:
    try:
        raw = path.read_bytes()
    except FileNotFoundError as exc:
        raise error(path, "file not found") from exc
    except OSError as exc:
        raise error(path, f"cannot read ({exc.strerror or exc})") from exc
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(path, "not a text file") from exc


def _number_rows(text: str) -> list[list[float]] | None:
    """Rows of numbers (whitespace or commas), ``#`` comments and blank lines skipped."""
    rows = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        try:
            rows.append([float(v) for v in line.split()])
        except ValueError:
            return None
    return rows


def _validate_K(K: np.ndarray, path: object, error: type[InputError]) -> np.ndarray:
    if not np.all(np.isfinite(K)):
        raise error(path, "intrinsic matrix has NaN or Inf entries")
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9) or abs(K[1, 0]) > 1e-9:
        raise error(
            path,
            "intrinsic matrix is not [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (transposed?)",
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise error(path, f"focal lengths must be positive (fx={K[0, 0]:g}, fy={K[1, 1]:g})")
    return K


def _read_K(
    path: Path, error: type[InputError] = DatasetError
) -> tuple[np.ndarray, tuple[int, int] | None]:
    """Intrinsics file -> ``(K (3, 3) float64, (H, W) or None)``.

    Open3D ``PinholeCameraIntrinsic`` JSON (``intrinsic_matrix`` column-major; also inside a
    ``PinholeCameraParameters`` file's ``intrinsic``), or text holding a 3x3 matrix or
    ScanNet's 4x4 one (its top-left 3x3).
    """
    text = _read_text(path, error)
    if path.suffix.lower() == ".json" or text.lstrip().startswith("{"):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise error(path, f"not valid JSON (line {exc.lineno}: {exc.msg})") from exc
        if isinstance(data, dict) and "intrinsic_matrix" not in data and "intrinsic" in data:
            data = data["intrinsic"]
        values = data.get("intrinsic_matrix") if isinstance(data, dict) else None
        if (
            not isinstance(values, list)
            or len(values) != 9
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
        ):
            raise error(path, "expected Open3D intrinsics JSON with 9 numbers 'intrinsic_matrix'")
        K = np.array(values, dtype=np.float64).reshape(3, 3, order="F")  # column-major
        shape = None
        width, height = data.get("width"), data.get("height")
        if isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0:
            shape = (height, width)
        return _validate_K(K, path, error), shape
    rows = _number_rows(text)
    if rows is None:
        raise error(path, "intrinsics text holds something other than numbers")
    widths = {len(r) for r in rows}
    if len(rows) == 4 and widths == {4}:  # ScanNet intrinsic_depth.txt: K padded to 4x4
        return _validate_K(np.array(rows, dtype=np.float64)[:3, :3].copy(), path, error), None
    if len(rows) != 3 or widths != {3}:
        raise error(path, "expected a 3x3 (or ScanNet 4x4) intrinsic matrix")
    return _validate_K(np.array(rows, dtype=np.float64), path, error), None


def _override_K(intrinsics: Any) -> tuple[np.ndarray, tuple[int, int] | None, str]:
    """Explicit intrinsics: a file, a ``(3, 3)`` array, or an object with a ``K`` attribute."""
    if isinstance(intrinsics, str | os.PathLike):
        path = Path(intrinsics)
        K, shape = _read_K(path, InputError)
        return K, shape, str(path)
    K = np.asarray(getattr(intrinsics, "K", intrinsics), dtype=np.float64)
    if K.shape != (3, 3):
        raise ShapeError(f"intrinsics must be a file or a (3, 3) matrix, got shape {K.shape}")
    return _validate_K(K.copy(), "intrinsics", InputError), None, "override"


def _is_rigid(T: np.ndarray) -> bool:
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        return False
    R = T[:3, :3]
    return bool(np.abs(R.T @ R - np.eye(3)).max() < 1e-2 and np.linalg.det(R) > 0)


def _read_pose(path: Path) -> np.ndarray | None:
    """4x4 camera-to-world text file, or None when absent, unreadable or not rigid."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError):
        return None
    rows = _number_rows(text)
    if rows is None or len(rows) != 4 or {len(r) for r in rows} != {4}:
        return None
    T = np.array(rows, dtype=np.float64)
    return T if _is_rigid(T) else None


def _quaternion_pose(values: list[float]) -> np.ndarray | None:
    """``tx ty tz qx qy qz qw`` -> 4x4 ``T_world_cam``, or None when invalid."""
    t = np.array(values[:3], dtype=np.float64)
    q = np.array(values[3:7], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not (np.all(np.isfinite(t)) and np.isfinite(norm) and norm > 1e-6):
        return None
    x, y, z, w = q / norm
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = t
    return T


def _natural_key(name: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name))


def _list_dir(path: Path) -> list[str]:
    try:
        return sorted(entry.name for entry in os.scandir(path))
    except OSError:
        return []


# ================================================================== TUM


def _read_tum_list(path: Path, skipped: list[SkippedFrame]) -> list[tuple[float, list[str]]]:
    """``timestamp value...`` lines (``#`` comments) -> ``[(stamp, values)]`` sorted by stamp."""
    entries = []
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
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
        entries.append((stamp, fields[1:]))
    entries.sort(key=lambda e: e[0])
    return entries


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


def _tum_frames(
    folder: Path, max_time_difference: float, pose_tolerance: float
) -> tuple[list[RGBDFrame], list[SkippedFrame]]:
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

    gt_t = np.zeros(0)
    gt_poses: list[np.ndarray | None] = []
    gt_path = folder / "groundtruth.txt"
    if gt_path.is_file():
        gt_skipped: list[SkippedFrame] = []  # bad ground-truth lines only cost poses
        entries = [e for e in _read_tum_list(gt_path, gt_skipped) if len(e[1]) >= 7]
        gt_t = np.array([e[0] for e in entries], dtype=np.float64)
        for _stamp, values in entries:
            try:
                gt_poses.append(_quaternion_pose([float(v) for v in values[:7]]))
            except ValueError:
                gt_poses.append(None)

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
        pose = gt_poses[k] if k is not None else None
        frames.append(RGBDFrame(i, depth_path, color_path, pose, stamp))
    return frames, skipped


def _freiburg_K(folder: Path, root: Path) -> tuple[np.ndarray, str] | None:
    for part in _names_up_to(folder, root):
        m = _FREIBURG.search(part)
        if m:
            fx, fy, cx, cy = TUM_INTRINSICS[int(m.group(1))]
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            return K, f"freiburg{m.group(1)} (published)"
    return None


# ================================================================== other layouts


def _3dmatch_frames(folder: Path, names: list[str]) -> tuple[list[RGBDFrame], list[SkippedFrame]]:
    present = set(names)
    numbered = []
    for name in names:
        m = _FRAME_3DMATCH.match(name)
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
        pose = _read_pose(folder / pose_name) if pose_name in present else None
        frames.append(RGBDFrame(number, folder / (stem + ".depth.png"), color, pose, None))
    return frames, []


def _images_by_stem(folder: Path) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for name in _list_dir(folder):
        stem, ext = os.path.splitext(name)
        if ext.lower() in _IMAGE_EXTS and stem not in out:
            out[stem] = folder / name
    return out


def _scannet_frames(folder: Path) -> tuple[list[RGBDFrame], list[SkippedFrame]]:
    depth = {s: p for s, p in _images_by_stem(folder / "depth").items() if p.suffix == ".png"}
    color = _images_by_stem(folder / "color")
    poses = set(_list_dir(folder / "pose"))
    frames = []
    for stem in sorted(depth, key=_natural_key):
        number = int(stem) if stem.isdigit() else len(frames)
        pose = _read_pose(folder / "pose" / f"{stem}.txt") if f"{stem}.txt" in poses else None
        frames.append(RGBDFrame(number, depth[stem], color.get(stem), pose, None))
    return frames, []


def _redwood_frames(folder: Path) -> tuple[list[RGBDFrame], list[SkippedFrame]]:
    depth = {s: p for s, p in _images_by_stem(folder / "depth").items() if p.suffix == ".png"}
    color: dict[str, Path] = {}
    for name in _COLOR_DIRS:
        if (folder / name).is_dir():
            color = _images_by_stem(folder / name)
            if color:
                break
    depth_stems = sorted(depth, key=_natural_key)
    color_stems = sorted(color, key=_natural_key)
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
        for s in sorted(set(color_stems) - set(pairing.values()), key=_natural_key)
    ]
    return frames, skipped


# ================================================================== discovery


def _names_up_to(folder: Path, root: Path) -> list[str]:
    """Names of ``folder`` and its ancestors up to ``root`` (inclusive), innermost first."""
    names = []
    current = folder
    while True:
        names.append(current.name)
        if current == root or current.parent == current:
            break
        current = current.parent
    return names


def _find_up(folder: Path, root: Path, filenames: Iterable[str], parent: bool) -> Path | None:
    """First of ``filenames`` in ``folder`` or an ancestor up to ``root`` (and the parent)."""
    dirs = []
    current = folder
    while True:
        dirs.append(current)
        if current == root or current.parent == current:
            break
        current = current.parent
    if parent and folder.parent not in dirs:
        dirs.append(folder.parent)
    for directory in dirs:
        for name in filenames:
            if (directory / name).is_file():
                return directory / name
    return None


def _detect(folder: Path, names: list[str]) -> str | None:
    present = set(names)
    if "depth.txt" in present and (folder / "depth.txt").is_file():
        return "tum"
    if any(_FRAME_3DMATCH.match(n) for n in names):
        return "3dmatch"
    if "depth" in present and (folder / "depth").is_dir():
        if ("intrinsic" in present and (folder / "intrinsic").is_dir()) or (
            "pose" in present and (folder / "pose").is_dir()
        ):
            return "scannet"
        return "redwood"
    return None


def _walk(root: Path) -> list[tuple[Path, str, list[str]]]:
    """Sequence folders under ``root``: ``[(folder, layout, entry names)]``, sorted."""
    found = []
    seen: set[str] = set()

    def visit(folder: Path) -> None:
        real = os.path.realpath(folder)
        if real in seen:
            return
        seen.add(real)
        names = _list_dir(folder)
        layout = _detect(folder, names)
        if layout is not None:
            found.append((folder, layout, names))
            if layout != "3dmatch":
                return  # the sequence's own sub-folders (rgb/, depth/, ...) hold no sequence
        for name in names:
            child = folder / name
            if not name.startswith(".") and child.is_dir():
                visit(child)

    visit(root)
    return found


def _sequence_K(
    folder: Path, root: Path, layout: str
) -> tuple[np.ndarray, tuple[int, int] | None, str]:
    if layout == "tum":
        path = folder / "intrinsics.json"
        if path.is_file():
            K, shape = _read_K(path)
            return K, shape, str(path)
        named = _freiburg_K(folder, root)
        if named is not None:
            return named[0], None, named[1]
        raise DatasetError(
            folder,
            "TUM sequence without intrinsics: no intrinsics.json and no freiburg1/2/3 (fr1/2/3) "
            "in the folder names; give the intrinsics explicitly",
        )
    if layout == "3dmatch":
        path = _find_up(folder, root, ["camera-intrinsics.txt"], parent=True)
        what = "camera-intrinsics.txt (in the sequence folder or its parent)"
    elif layout == "scannet":
        path = folder / "intrinsic" / "intrinsic_depth.txt"
        path = path if path.is_file() else None
        what = "intrinsic/intrinsic_depth.txt (the colour intrinsics are not used for depth)"
    else:
        path = _find_up(folder, root, _REDWOOD_INTRINSICS, parent=False)
        what = "intrinsic.json or camera_intrinsic.json"
    if path is None:
        raise DatasetError(
            folder, f"{layout} sequence without {what}; give the intrinsics explicitly"
        )
    K, shape = _read_K(path)
    return K, shape, str(path)


def _probe_shape(frames: list[RGBDFrame], tries: int = 5) -> tuple[int, int] | None:
    for frame in frames[:tries]:
        try:
            return _image_shape(frame.depth_path)
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
    max_time_difference: float = 0.02,
    pose_time_tolerance: float = 0.02,
    verify: bool = False,
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
            (:data:`DEFAULT_DEPTH_SCALE`: 5000 TUM, 1000 the others).
        require_color: keep only frames with colour; sequences without colour are dropped.
        require_poses: keep only frames with a valid pose.
        max_time_difference: TUM rgb-depth association limit, seconds.
        pose_time_tolerance: TUM ground-truth association limit, seconds.
        verify: decode every image now (slow) instead of failing at read time.

    Returns:
        The sequences (never empty).

    Raises:
        DatasetError: ``root`` is missing or not a folder; no sequence (or none with colour,
            with poses, or with a frame) is found; a sequence has no intrinsics, unreadable
            intrinsics, or intrinsics for another image size; ``depth.txt`` is unreadable.
        InputError: the ``intrinsics`` file cannot be used.
        ShapeError: ``intrinsics`` is an array that is not 3x3.
        ValueError: ``depth_scale`` or a tolerance is not a positive number.
    """
    root = Path(root)
    if not root.exists():
        raise DatasetError(root, "folder does not exist")
    if not root.is_dir():
        raise DatasetError(root, "not a folder")
    if depth_scale is not None and not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale must be positive (raw units per metre), got {depth_scale}")
    for label, value in (
        ("max_time_difference", max_time_difference),
        ("pose_time_tolerance", pose_time_tolerance),
    ):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{label} must be a positive number of seconds, got {value}")
    override = _override_K(intrinsics) if intrinsics is not None else None

    sequences = []
    dropped = {"color": 0, "poses": 0, "frames": 0}
    for folder, layout, names in _walk(root):
        if layout == "tum":
            frames, skipped = _tum_frames(folder, max_time_difference, pose_time_tolerance)
        elif layout == "3dmatch":
            frames, skipped = _3dmatch_frames(folder, names)
        elif layout == "scannet":
            frames, skipped = _scannet_frames(folder)
        else:
            frames, skipped = _redwood_frames(folder)
        if override is not None:
            K, shape, source = override
        else:
            K, shape, source = _sequence_K(folder, root, layout)
        rel = folder.relative_to(root).as_posix()
        seq = RGBDSequence(
            root=folder,
            name=root.name if rel == "." else rel,
            layout=layout,
            frames=frames,
            K=K,
            depth_scale=float(depth_scale or DEFAULT_DEPTH_SCALE[layout]),
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
        raise DatasetError(root, _NOT_FOUND)
    return sequences


# ================================================================== pairs


def make_pairs(num_frames: int, spacing: int = 20, mode: str = "train") -> list[tuple[int, int]]:
    """Frame pairs of one sequence (method.md section 1).

    ``"train"``: every frame ``i`` with ``i + spacing`` (all starts). ``"val"``: every
    ``spacing``-th frame, consecutive ones paired: ``(0, s), (s, 2s), ...``.

    Args:
        num_frames: number of (valid) frames of the sequence.
        spacing: frames between the two views, >= 1.
        mode: ``"train"`` or ``"val"``.

    Returns:
        ``[(i, j)]`` with ``j = i + spacing < num_frames``, increasing ``i``; empty when the
        sequence is too short.

    Raises:
        ValueError: ``num_frames < 0``, ``spacing < 1`` or an unknown ``mode``.
    """
    num_frames, spacing = int(num_frames), int(spacing)
    if num_frames < 0:
        raise ValueError(f"num_frames must be >= 0, got {num_frames}")
    if spacing < 1:
        raise ValueError(f"spacing must be >= 1, got {spacing}")
    if mode == "train":
        starts = range(0, max(0, num_frames - spacing))
    elif mode == "val":
        starts = range(0, max(0, num_frames - spacing), spacing)
    else:
        raise ValueError(f"mode must be 'train' or 'val', got {mode!r}")
    return [(i, i + spacing) for i in starts]


# ================================================================== preprocessing


def preprocess_frame(
    depth_m: np.ndarray, color: np.ndarray | None, K: np.ndarray, size: int = 128
) -> PreprocessedFrame:
    """Centre-crop a frame to a square and resize it to ``size x size`` (method.md section 1).

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


def backproject(depth_m: np.ndarray, K: np.ndarray) -> BackProjection:
    """Back-project a depth image through pixel centres, dropping missing depth.

    Pixel ``(u, v)`` with depth ``z > 0`` gives ``z * K^-1 [u + 0.5, v + 0.5, 1]`` (OpenCV
    axes). Points come in row-major pixel order; ``pixel_index = v * W + u`` lets each point
    read its own pixel of an ``(H, W)`` feature map.

    Args:
        depth_m: ``(H, W)`` depth in metres; ``<= 0`` and non-finite are missing.
        K: ``(3, 3)`` intrinsics.

    Returns:
        :class:`BackProjection` ``(points (N, 3) float32, pixel_index (N,) int64)``.

    Raises:
        ShapeError: ``depth_m`` not 2-D or ``K`` not 3x3.
        ValueError: ``K`` not finite and invertible.
    """
    depth_m = np.asarray(depth_m)
    K = np.asarray(K, dtype=np.float64)
    if depth_m.ndim != 2:
        raise ShapeError(f"depth_m must be (H, W), got {depth_m.shape}")
    if K.shape != (3, 3):
        raise ShapeError(f"K must be (3, 3), got {K.shape}")
    if not np.all(np.isfinite(K)) or abs(np.linalg.det(K)) < 1e-12:
        raise ValueError("K must be a finite invertible matrix")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth_m) & (depth_m > 0)
    pixel_index = np.flatnonzero(valid).astype(np.int64)
    v, u = np.divmod(pixel_index, depth_m.shape[1])
    z = depth_m.reshape(-1)[pixel_index].astype(np.float64)
    rays = np.stack([u + 0.5, v + 0.5, np.ones_like(z)], axis=1) @ np.linalg.inv(K).T
    return BackProjection((rays * z[:, None]).astype(np.float32), pixel_index)
