"""A given trajectory of the frames being tracked (wheel odometry, an IMU, an earlier run) as
the motion prior of ``odometry --init-poses``.

Frames are matched to the trajectory's poses by timestamp (the nearest pose within
:data:`STAMP_TOLERANCE`, the ``max_difference`` of the TUM benchmark's ``associate.py``) or by
id (a ``.log``'s first header number against the frame's number). The prior of a frame is the
given trajectory's motion from the previous frame, ``inv(G_prev) @ G_frame``: it does not
depend on where the given trajectory puts its world.

Depends on numpy only.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import numpy as np

#: a frame takes the given pose nearest in time when it lies at most this far, seconds
STAMP_TOLERANCE = 0.02


def poses_by_stamp(
    stamps: np.ndarray,
    poses: np.ndarray,
    wanted: Sequence[float],
    tolerance: float = STAMP_TOLERANCE,
) -> list[np.ndarray | None]:
    """Per ``wanted`` stamp, the pose of ``poses (N, 4, 4)`` whose stamp (``stamps (N,)``,
    sorted) is nearest, or None when none lies within ``tolerance``."""
    stamps = np.asarray(stamps, dtype=np.float64)
    out: list[np.ndarray | None] = []
    if len(stamps) == 0:
        return [None] * len(wanted)
    for t in wanted:
        k = int(np.searchsorted(stamps, t))
        near = [n for n in (k - 1, k) if 0 <= n < len(stamps)]
        best = min(near, key=lambda n: abs(stamps[n] - t))
        out.append(poses[best] if abs(stamps[best] - t) <= tolerance else None)
    return out


def poses_by_id(
    ids: np.ndarray, poses: np.ndarray, wanted: Sequence[int]
) -> list[np.ndarray | None]:
    """Per ``wanted`` id, the pose of ``poses (N, 4, 4)`` with that id (``ids (N,)``; the
    last one when an id repeats), or None."""
    table = {int(i): pose for i, pose in zip(ids, poses, strict=True)}
    return [table.get(int(i)) for i in wanted]


def relative_motions(given: Sequence[np.ndarray | None]) -> list[np.ndarray | None]:
    """Per frame, ``inv(G_prev) @ G_frame`` (``T_prev_frame``) of the given poses, or None
    (the first frame, or either pose missing)."""
    out: list[np.ndarray | None] = [None]
    for before, now in pairwise(given):
        out.append(None if before is None or now is None else np.linalg.inv(before) @ now)
    return out
