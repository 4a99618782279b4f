"""Camera trajectories as text: the TUM RGB-D format and the 3DMatch / Redwood ``.log``.

A trajectory is a list of camera-to-world poses ``T_world_cam`` (4x4 float64, column vectors).

TUM (``groundtruth.txt``, what ``byoc odometry`` writes)
    One line per pose, ``timestamp tx ty tz qx qy qz qw``: the camera centre in the world
    and the unit quaternion of the rotation (Hamilton, scalar last), ``#`` comments allowed.
``.log`` (Open3D's ``write_pinhole_camera_trajectory``, 3DMatch's reconstructions)
    Per pose a header line ``i i i+1`` (or ``i j n``: the first number is the pose's id)
    then the 4x4 pose, one row per line.

:func:`read_trajectory` reads either (a ``.log`` by its suffix), as the initial poses of
``register-scans`` and ``odometry`` (``--init-poses``).

Numbers are written as the shortest decimal that reads back to the same float64 (the
quaternion of a pose is then exact to about 1e-16).

Depends on numpy and :mod:`byoc_cli.errors` only.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io.inputs import read_input

__all__ = [
    "GivenTrajectory",
    "format_trajectory_log",
    "format_tum_trajectory",
    "matrix_to_quaternion",
    "quaternion_to_matrix",
    "read_trajectory",
    "read_trajectory_log",
    "read_tum_trajectory",
]

#: Largest ``max |R^T R - I|`` of a pose that is written.
_ORTHONORMAL_TOL = 1e-3


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion ``q (4,)`` = ``(qx, qy, qz, qw)`` (normalised here).

    Raises:
        ShapeError: ``q`` is not 4 finite numbers of non-zero norm.
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(q)) if q.shape == (4,) else math.nan
    if not (np.isfinite(norm) and norm > 1e-6):
        raise ShapeError(f"a quaternion must be 4 finite numbers of non-zero norm, got {q}")
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(qx, qy, qz, qw)`` of a rotation ``R (3, 3)``, with ``qw >= 0``.

    Shepperd's method: the largest of ``|qw|, |qx|, |qy|, |qz|`` is taken from the diagonal,
    the others from the off-diagonal terms (stable for every angle, 180 degrees included).
    """
    R = np.asarray(R, dtype=np.float64)
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    diag = (trace, R[0, 0], R[1, 1], R[2, 2])
    k = int(np.argmax(diag))
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
        q = [s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 0.0))
        q = [(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 0.0))
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def _check_poses(poses: Sequence[np.ndarray]) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ShapeError(f"poses must be (N, 4, 4), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ShapeError("a pose has NaN or Inf entries")
    R = poses[:, :3, :3]
    error = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(initial=0.0)
    if error > _ORTHONORMAL_TOL:
        raise ShapeError(f"a pose's rotation is not orthonormal (max |R^T R - I| = {error:.2g})")
    return poses


def format_tum_trajectory(stamps: Sequence[float], poses: Sequence[np.ndarray]) -> str:
    """The TUM text of ``poses (N, 4, 4)`` at ``stamps (N,)`` (seconds or frame numbers).

    Raises:
        ShapeError: not one finite stamp per pose, or a pose is not rigid.
    """
    poses = _check_poses(poses)
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    if len(stamps) != len(poses) or not np.all(np.isfinite(stamps)):
        raise ShapeError(f"need one finite stamp per pose: {len(stamps)} for {len(poses)}")
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, pose in zip(stamps, poses, strict=True):
        values = [*pose[:3, 3], *matrix_to_quaternion(pose[:3, :3])]
        lines.append(" ".join([_number(stamp), *(repr(float(v)) for v in values)]))
    return "\n".join(lines) + "\n"


def _number(stamp: float) -> str:
    """A stamp as written: integers without a fraction (frame numbers), else the shortest."""
    return str(int(stamp)) if float(stamp).is_integer() else repr(float(stamp))


def read_tum_trajectory(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Returns:
        ``(stamps (N,), poses (N, 4, 4))`` float64, sorted by stamp.

    Raises:
        InputError: unreadable, or a line is not 8 numbers with a valid quaternion.
    """
    path = Path(path)
    try:
        text = read_input(path, "trajectory").decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(path, f"cannot read it ({exc})") from exc
    stamps, poses = [], []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values = [float(v) for v in line.replace(",", " ").split()]
            if len(values) != 8 or not all(math.isfinite(v) for v in values):
                raise ValueError
            pose = np.eye(4)
            pose[:3, :3] = quaternion_to_matrix(np.asarray(values[4:]))
        except (ValueError, ShapeError) as exc:
            raise InputError(
                path, f"line {number} is not 'timestamp tx ty tz qx qy qz qw'"
            ) from exc
        pose[:3, 3] = values[1:4]
        stamps.append(values[0])
        poses.append(pose)
    order = np.argsort(np.asarray(stamps), kind="stable")
    return np.asarray(stamps, np.float64)[order], np.asarray(poses, np.float64).reshape(-1, 4, 4)[
        order
    ]


def format_trajectory_log(poses: Sequence[np.ndarray], ids: Sequence[int] | None = None) -> str:
    """The ``.log`` text of ``poses (N, 4, 4)``: per pose ``i i i+1`` then its 4 rows.

    Args:
        poses: ``T_world_cam`` per pose.
        ids: the number ``i`` of each pose (default ``0 .. N-1``).

    Raises:
        ShapeError: a pose is not rigid, or not one id per pose.
    """
    poses = _check_poses(poses)
    ids = list(range(len(poses))) if ids is None else [int(i) for i in ids]
    if len(ids) != len(poses):
        raise ShapeError(f"need one id per pose: {len(ids)} for {len(poses)}")
    records = []
    for i, pose in zip(ids, poses, strict=True):
        rows = "".join(" ".join(repr(float(x)) for x in row) + "\n" for row in pose)
        records.append(f"{i} {i} {i + 1}\n{rows}")
    return "".join(records)


def read_trajectory_log(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a ``.log`` trajectory: per pose a line of 3 integers (the first is the pose's id),
    then 4 rows of 4 numbers; blank lines are skipped.

    Returns:
        ``(ids (N,) int64, poses (N, 4, 4) float64)`` in file order.

    Raises:
        InputError: unreadable, no pose, a header or row of the wrong count or not numbers, a
            truncated record, or a matrix that is not a rigid transform.
    """
    path = Path(path)
    try:
        text = read_input(path, "trajectory").decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(path, f"cannot read it ({exc})") from exc
    lines = [(k, line.split()) for k, line in enumerate(text.splitlines(), 1) if line.strip()]
    if len(lines) % 5:
        number = lines[len(lines) - len(lines) % 5][0]
        raise InputError(path, f"line {number}: record truncated (a line 'i i n' and 4 rows)")
    ids, poses = [], []
    for start in range(0, len(lines), 5):
        (number, header), rows = lines[start], lines[start + 1 : start + 5]
        if len(header) != 3 or not all(v.lstrip("-").isdigit() for v in header):
            raise InputError(path, f"line {number}: expected a header of 3 integers 'i i n'")
        T = np.eye(4)
        for r, (row_number, row) in enumerate(rows):
            try:
                T[r] = [float(v) for v in row]
            except ValueError as exc:
                raise InputError(path, f"line {row_number}: expected 4 numbers") from exc
        try:
            _check_poses([T])
        except ShapeError as exc:
            raise InputError(path, f"line {number}: the pose is not rigid ({exc})") from exc
        if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
            raise InputError(path, f"line {number + 4}: the last row is not '0 0 0 1'")
        ids.append(int(header[0]))
        poses.append(T)
    if not poses:
        raise InputError(path, "holds no pose")
    return np.asarray(ids, np.int64), np.asarray(poses, np.float64)


class GivenTrajectory(NamedTuple):
    """A trajectory read by :func:`read_trajectory`.

    Attributes:
        format: ``"tum"`` or ``"log"``.
        keys: per pose its timestamp (TUM, seconds or frame numbers) or its id (``.log``).
        poses: ``(N, 4, 4)`` float64 ``T_world_cam``; TUM poses sorted by stamp, ``.log``
            poses in file order.
    """

    format: str
    keys: np.ndarray
    poses: np.ndarray


def read_trajectory(path: str | os.PathLike[str]) -> GivenTrajectory:
    """A TUM trajectory or (suffix ``.log``) a ``.log`` one.

    Raises:
        InputError: unreadable, malformed (the line is named) or without a pose.
    """
    if Path(path).suffix.lower() == ".log":
        ids, poses = read_trajectory_log(path)
        return GivenTrajectory("log", ids, poses)
    stamps, poses = read_tum_trajectory(path)
    if not len(poses):
        raise InputError(Path(path), "holds no pose (TUM: 'timestamp tx ty tz qx qy qz qw')")
    return GivenTrajectory("tum", stamps, poses)
