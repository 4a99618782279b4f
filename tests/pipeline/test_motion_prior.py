"""A given trajectory matched to frames: by timestamp within a tolerance, by id; its motions."""

from __future__ import annotations

import numpy as np

from byoc_cli.pipeline.motion_prior import (
    STAMP_TOLERANCE,
    poses_by_id,
    poses_by_stamp,
    relative_motions,
)


def _shifts(*xs: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (len(xs), 1, 1))
    poses[:, 0, 3] = xs
    return poses


def test_the_nearest_stamp_within_the_tolerance():
    stamps, poses = np.array([0.0, 0.01, 0.05, 1.0]), _shifts(0, 1, 2, 3)
    got = poses_by_stamp(stamps, poses, [0.004, 0.006, 0.036, 0.5, 1.019, 1.03, -0.5])
    assert [None if p is None else p[0, 3] for p in got] == [0, 1, 2, None, 3, None, None]
    assert STAMP_TOLERANCE == 0.02  # the TUM benchmark's associate.py
    assert poses_by_stamp(np.zeros(0), np.zeros((0, 4, 4)), [1.0]) == [None]


def test_by_id():
    got = poses_by_id(np.array([3, 1, 7]), _shifts(30, 10, 70), [1, 2, 3, 7])
    assert [None if p is None else p[0, 3] for p in got] == [10, None, 30, 70]


def test_motions_do_not_depend_on_the_given_world():
    rng = np.random.default_rng(0)
    poses = [np.eye(4) for _ in range(4)]
    for pose in poses:
        pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        pose[:3, :3] *= np.sign(np.linalg.det(pose[:3, :3]))
        pose[:3, 3] = rng.normal(size=3)
    world = np.eye(4)
    world[:3, 3] = [100.0, -5.0, 2.0]
    moved = relative_motions([world @ p for p in poses])
    plain = relative_motions(poses)
    assert moved[0] is None and plain[0] is None
    for a, b, k in zip(moved[1:], plain[1:], range(1, 4), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)
        np.testing.assert_allclose(poses[k - 1] @ b, poses[k], atol=1e-12)
    assert relative_motions([poses[0], None, poses[2]])[1:] == [None, None]
