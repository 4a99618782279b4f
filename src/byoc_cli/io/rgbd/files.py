"""File helpers shared by the layout readers: text, intrinsics and pose files, folder listings.

Intrinsics files: Open3D ``PinholeCameraIntrinsic`` JSON (``intrinsic_matrix`` column-major,
also inside a ``PinholeCameraParameters`` file's ``intrinsic``), or text holding a 3x3 matrix
or ScanNet's 4x4 one. Pose files: a 4x4 camera-to-world matrix as text; an invalid pose
(non-finite, not rigid) reads as None.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from byoc_cli.errors import DatasetError, InputError, ShapeError
from byoc_cli.io.inputs import read_input

#: Image file extensions of the folder layouts (ScanNet, Redwood).
IMAGE_EXTS = (".png", ".jpg", ".jpeg")


def read_text(path: Path, error: type[InputError] = DatasetError, kind: str = "listing") -> str:
    """The UTF-8 text of ``path`` (a regular file within the cap of ``kind``)."""
    raw = read_input(path, kind, error)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(path, "not a text file") from exc


def number_rows(text: str) -> list[list[float]] | None:
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


def validate_K(K: np.ndarray, path: object, error: type[InputError]) -> np.ndarray:
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


def read_K(
    path: Path, error: type[InputError] = DatasetError
) -> tuple[np.ndarray, tuple[int, int] | None]:
    """Intrinsics file -> ``(K (3, 3) float64, (H, W) or None)``.

    Open3D ``PinholeCameraIntrinsic`` JSON (``intrinsic_matrix`` column-major; also inside a
    ``PinholeCameraParameters`` file's ``intrinsic``), or text holding a 3x3 matrix or
    ScanNet's 4x4 one (its top-left 3x3).
    """
    text = read_text(path, error, "intrinsics")
    if path.suffix.lower() == ".json" or text.lstrip().startswith("{"):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise error(path, f"not valid JSON (line {exc.lineno}: {exc.msg})") from exc
        except RecursionError as exc:
            raise error(path, "not valid JSON (nested too deeply)") from exc
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
        return validate_K(K, path, error), shape
    rows = number_rows(text)
    if rows is None:
        raise error(path, "intrinsics text holds something other than numbers")
    widths = {len(r) for r in rows}
    if len(rows) == 4 and widths == {4}:  # ScanNet intrinsic_depth.txt: K padded to 4x4
        return validate_K(np.array(rows, dtype=np.float64)[:3, :3].copy(), path, error), None
    if len(rows) != 3 or widths != {3}:
        raise error(path, "expected a 3x3 (or ScanNet 4x4) intrinsic matrix")
    return validate_K(np.array(rows, dtype=np.float64), path, error), None


def override_K(intrinsics: Any) -> tuple[np.ndarray, tuple[int, int] | None, str]:
    """Explicit intrinsics: a file, a ``(3, 3)`` array, or an object with a ``K`` attribute."""
    if isinstance(intrinsics, str | os.PathLike):
        path = Path(intrinsics)
        K, shape = read_K(path, InputError)
        return K, shape, str(path)
    K = np.asarray(getattr(intrinsics, "K", intrinsics), dtype=np.float64)
    if K.shape != (3, 3):
        raise ShapeError(f"intrinsics must be a file or a (3, 3) matrix, got shape {K.shape}")
    return validate_K(K.copy(), "intrinsics", InputError), None, "override"


def is_rigid(T: np.ndarray) -> bool:
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        return False
    R = T[:3, :3]
    return bool(np.abs(R.T @ R - np.eye(3)).max() < 1e-2 and np.linalg.det(R) > 0)


def read_pose(path: Path) -> np.ndarray | None:
    """4x4 camera-to-world text file, or None when absent, unreadable or not rigid."""
    try:
        text = read_input(path, "matrix").decode("utf-8-sig")
    except (InputError, UnicodeDecodeError):
        return None
    rows = number_rows(text)
    if rows is None or len(rows) != 4 or {len(r) for r in rows} != {4}:
        return None
    T = np.array(rows, dtype=np.float64)
    return T if is_rigid(T) else None


def natural_key(name: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name))


def list_dir(path: Path) -> list[str]:
    try:
        return sorted(entry.name for entry in os.scandir(path))
    except OSError:
        return []


def images_by_stem(folder: Path) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for name in list_dir(folder):
        stem, ext = os.path.splitext(name)
        if ext.lower() in IMAGE_EXTS and stem not in out:
            out[stem] = folder / name
    return out


def names_up_to(folder: Path, root: Path) -> list[str]:
    """Names of ``folder`` and its ancestors up to ``root`` (inclusive), innermost first."""
    names = []
    current = folder
    while True:
        names.append(current.name)
        if current == root or current.parent == current:
            break
        current = current.parent
    return names


def find_up(folder: Path, root: Path, filenames: Iterable[str], parent: bool) -> Path | None:
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


def layout_intrinsics(
    folder: Path, layout: str, path: Path | None, what: str
) -> tuple[np.ndarray, tuple[int, int] | None, str]:
    """Read a layout's intrinsics file found at ``path``.

    Args:
        folder: the sequence folder (for the error).
        layout: the layout name (for the error).
        path: the file, or None when the layout's search found none.
        what: the file(s) looked for, e.g. ``"intrinsic.json or camera_intrinsic.json"``.

    Returns:
        ``(K (3, 3) float64, (H, W) or None, source)`` with ``source`` the file name.

    Raises:
        DatasetError: no file, or an unreadable one.
    """
    if path is None:
        raise DatasetError(
            folder, f"{layout} sequence without {what}; give the intrinsics explicitly"
        )
    K, shape = read_K(path)
    return K, shape, str(path)
