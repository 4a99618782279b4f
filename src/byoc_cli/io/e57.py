"""E57 files (ASTM E2807, terrestrial scanner exports), read and written with pye57.

An E57 file holds one or more scans (its ``data3D`` list). Each scan stores its points in
its own frame (cartesian, or spherical range/azimuth/elevation) and, optionally, a pose: the
rigid transform ``T_file_scan`` (a unit quaternion and a translation) that brings them into
the file's frame, where georeferenced exports keep their large coordinates.

What the reader returns: the points of one scan in the **file's frame** (the scan's pose
applied, in float64), as CloudCompare, PDAL and pye57 show them; points flagged invalid
(``cartesianInvalidState`` / ``sphericalInvalidState`` non-zero) are left out. So a T that
``byoc register`` computes between two E57 scans is in the file's coordinates, and scans that
the scanner's software already placed start ``register-scans`` at their stored poses.
:func:`read_e57_poses` gives each scan's stored pose as ``T_file_scan`` (4x4), and
``apply_pose=False`` reads a scan in its own frame, for a caller that wants to use the poses
itself.

A file with several scans is read one scan at a time (``site.e57:2``, see
:mod:`byoc_cli.io.cloudpath`); reading such a file as one cloud is refused with the way to
pick a scan.

pye57 is imported lazily (``pip install pye57``); its absence is an
:class:`~byoc_cli.errors.InputError` naming the file and the install command.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io.atomic import atomic_write, temp_sibling, write_errors
from byoc_cli.io.cloudpath import parse_cloud_path, scan_path
from byoc_cli.io.inputs import check_input, check_point_count

__all__ = [
    "e57_scan_count",
    "expand_scans",
    "read_e57_points",
    "read_e57_poses",
    "write_e57",
]

_INSTALL = "pip install pye57"
#: a written scan's origin (kept in its pose, in float64) is rounded to whole steps of this,
#: in the points' units; its float32 coordinates are taken relative to it
_ORIGIN_STEP = 1.0


def _pye57(path: object) -> Any:
    """Import pye57, or an :class:`InputError` naming ``path`` with the install command."""
    try:
        import pye57
    except ImportError as exc:
        raise InputError(path, f"reading E57 needs pye57; install it with `{_INSTALL}`") from exc
    return pye57


def _first_line(exc: BaseException) -> str:
    """libE57Format's messages carry a debug report after the first line: keep the first."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


@contextlib.contextmanager
def _opened(path: Path):
    """The E57 file at ``path`` open for reading (a regular file within the cloud cap);
    libE57Format's errors become :class:`InputError`."""
    pye57 = _pye57(path)
    check_input(path, "cloud")
    try:
        e57 = pye57.E57(str(path))
    except MemoryError:
        raise
    except Exception as exc:
        raise InputError(path, f"not a readable E57 file ({_first_line(exc)})") from exc
    try:
        yield e57
    except (InputError, MemoryError):
        raise
    except Exception as exc:  # libE57Format, pye57 (ValueError, bare Exception)
        raise InputError(path, f"corrupt E57 file ({_first_line(exc)})") from exc
    finally:
        e57.close()


def e57_scan_count(path: str | os.PathLike[str]) -> int:
    """How many scans the E57 file ``path`` holds.

    Raises:
        InputError: the file is missing, not E57, or pye57 is not installed.
    """
    with _opened(Path(path)) as e57:
        return int(e57.scan_count)


def expand_scans(paths: list[Path]) -> list[Path]:
    """``paths`` with every E57 file of several scans replaced by its scans, in the file's
    order (``site.e57`` of 3 scans -> ``site.e57:0``, ``site.e57:1``, ``site.e57:2``); other
    paths (one-scan E57 files and ``site.e57:K`` included) are kept as they are.

    Raises:
        InputError: an E57 file cannot be read (see :func:`e57_scan_count`).
    """
    expanded: list[Path] = []
    for path in paths:
        file, scan = parse_cloud_path(path)
        count = 1
        if scan is None and file.suffix.lower() == ".e57":
            count = e57_scan_count(file)
        if count > 1:
            expanded += [scan_path(file, k) for k in range(count)]
        else:
            expanded.append(Path(path))
    return expanded


def _pose(header: Any) -> np.ndarray:
    """``T_file_scan`` (4x4 float64) of a scan header; the identity when it has no pose."""
    T = np.eye(4)
    if not header.has_pose():
        return T
    q = np.asarray(header.rotation, dtype=np.float64)  # w, x, y, z
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"scan pose has an invalid rotation quaternion {q.tolist()}")
    w, x, y, z = q / norm
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = np.asarray(header.translation, dtype=np.float64)
    if not np.isfinite(T).all():
        raise ValueError("scan pose has a non-finite translation")
    return T


def read_e57_poses(
    path: str | os.PathLike[str], *, stored_only: bool = False
) -> list[np.ndarray | None]:
    """The stored pose of every scan of an E57 file, as ``T_file_scan``.

    Returns:
        One ``(4, 4)`` float64 per scan, in the file's order: ``x_file = R x_scan + t``
        (column vectors); for a scan that stores no pose, the identity (``stored_only``:
        None).

    Raises:
        InputError: the file cannot be read, or a pose is not a rotation and a translation.
    """
    with _opened(Path(path)) as e57:
        headers = [e57.get_header(k) for k in range(e57.scan_count)]
        return [None if stored_only and not h.has_pose() else _pose(h) for h in headers]


def _scan_points(e57: Any, index: int, path: Path) -> tuple[np.ndarray, Any]:
    """The valid points of scan ``index`` in the scan's own frame, float64, and its header."""
    from pye57.e57 import COORDINATE_SYSTEMS
    from pye57.utils import convert_spherical_to_cartesian

    header = e57.get_header(index)
    count = int(header.point_count)
    if count == 0:
        raise InputError(scan_path(path, index), "empty point cloud (0 points)")
    check_point_count(count, scan_path(path, index))
    system = header.get_coordinate_system(COORDINATE_SYSTEMS)
    data = e57.read_scan(index, transform=False, ignore_missing_fields=True)
    if system is COORDINATE_SYSTEMS.CARTESIAN:
        columns = [data[k] for k in ("cartesianX", "cartesianY", "cartesianZ")]
        points = np.column_stack([np.asarray(c, dtype=np.float64) for c in columns])
    else:
        rae = np.column_stack(
            [data[k] for k in ("sphericalRange", "sphericalAzimuth", "sphericalElevation")]
        )
        points = np.asarray(convert_spherical_to_cartesian(rae), dtype=np.float64)
    return points.reshape(-1, 3), header


def read_e57_points(
    path: str | os.PathLike[str], scan: int | None = None, *, apply_pose: bool = True
) -> np.ndarray:
    """The points of one scan of an E57 file, in float64.

    Args:
        path: the ``.e57`` file.
        scan: 0-based index of the scan; None: the file's only scan (a file with several
            scans is refused, naming them and how to pick one).
        apply_pose: True (default): in the file's frame (the scan's stored pose applied);
            False: in the scan's own frame.

    Returns:
        ``(N, 3)`` float64, the scan's valid points (N may be 0 when every point is flagged
        invalid; the caller refuses an empty cloud).

    Raises:
        InputError: naming the file (or ``file:scan``): missing, not E57, pye57 not installed,
            several scans and no ``scan``, ``scan`` out of range, no points, a header counting
            more points than byoc reads from one file, corrupt data.
    """
    path = Path(path)
    with _opened(path) as e57:
        count = int(e57.scan_count)
        if count == 0:
            raise InputError(path, "holds no scan (its data3D list is empty)")
        if scan is None and count > 1:
            raise InputError(
                path,
                f"holds {count} scans; give one as {scan_path(path, 0)} to "
                f"{scan_path(path, count - 1)} (0-based), or give the file to "
                "`byoc register-scans`, which takes each scan as a cloud",
            )
        index = 0 if scan is None else scan
        if not 0 <= index < count:
            raise InputError(
                scan_path(path, index),
                f"no such scan: the file holds {count} scan(s), 0 to {count - 1}",
            )
        points, header = _scan_points(e57, index, path)
        if apply_pose:
            T = _pose(header)
            points = points @ T[:3, :3].T + T[:3, 3]
    return points


def write_e57(path: str | os.PathLike[str], points: np.ndarray, name: str = "byoc") -> None:
    """Write ``points`` as one scan of a new E57 file, atomically.

    pye57 stores a written scan's coordinates as float32, so they are stored relative to an
    origin (the middle of the points' box, rounded to whole units) that the scan's pose
    holds in float64: a reader that applies the pose (CloudCompare, PDAL, :func:`read_e57_points`)
    gets the points back to float32 precision of their distance from that origin (0.1 mm at
    1 km), whatever their magnitude. Only x, y, z are written (no intensity or colour).

    Args:
        path: the output ``.e57`` file.
        points: ``(N, 3)`` finite real, N >= 1.
        name: the scan's name in the file.

    Raises:
        ShapeError: ``points`` is not finite ``(N, 3)`` with N >= 1.
        InputError: pye57 is not installed, or ``path`` cannot be written.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ShapeError(f"points must be (N, 3) with N >= 1, got {points.shape}")
    if not np.isfinite(points).all():
        raise ShapeError("points must be finite to be written to E57")
    path = Path(path)
    pye57 = _pye57(path)
    origin = np.round((points.min(axis=0) + points.max(axis=0)) / 2 / _ORIGIN_STEP) * _ORIGIN_STEP
    local = points - origin
    data = {f"cartesian{axis}": np.ascontiguousarray(local[:, j]) for j, axis in enumerate("XYZ")}
    # libE57Format writes to a name, not to a stream: into a hidden file beside the output,
    # then copied into the atomic write (which checks the folder first)
    with atomic_write(path, "wb") as out, write_errors(path):
        staged = temp_sibling(path, "e57")
        try:
            try:
                with pye57.E57(str(staged), mode="w") as e57:
                    e57.write_scan_raw(
                        data, name=name, rotation=np.array([1.0, 0, 0, 0]), translation=origin
                    )
            except MemoryError:
                raise
            except Exception as exc:
                raise InputError(path, f"cannot write it ({_first_line(exc)})") from exc
            with open(staged, "rb") as done:
                shutil.copyfileobj(done, out, 1 << 20)
        finally:
            with contextlib.suppress(OSError):
                os.unlink(staged)
