"""ATE and RPE as the TUM RGB-D benchmark scripts compute them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from byoc_cli.errors import ShapeError
from byoc_cli.evaluation.trajectory import (
    absolute_trajectory_error,
    align_rigid,
    relative_pose_error,
)
from byoc_cli.io.trajectory import quaternion_to_matrix


def _pose(R: np.ndarray | None = None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


def _rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def _random_trajectory(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = [np.eye(4)]
    for _ in range(n - 1):
        step = _pose(quaternion_to_matrix(np.r_[rng.normal(scale=0.05, size=3), 1.0]))
        step[:3, 3] = rng.normal(scale=0.05, size=3)
        poses.append(poses[-1] @ step)
    return np.asarray(poses)


# ------------------------------------------------------------------ naive references
# evaluate_ate.py's align() and evaluate_rpe.py's fixed-delta loop, transcribed


def _tum_align(model: np.ndarray, data: np.ndarray) -> np.ndarray:
    """evaluate_ate.align: model, data 3xn; returns the per-point errors."""
    model_zc = model - model.mean(1, keepdims=True)
    data_zc = data - data.mean(1, keepdims=True)
    W = np.zeros((3, 3))
    for column in range(model.shape[1]):
        W += np.outer(model_zc[:, column], data_zc[:, column])
    U, _, Vh = np.linalg.svd(W.transpose())
    S = np.identity(3)
    if np.linalg.det(U) * np.linalg.det(Vh) < 0:
        S[2, 2] = -1
    rot = U @ S @ Vh
    trans = data.mean(1, keepdims=True) - rot @ model.mean(1, keepdims=True)
    error = rot @ model + trans - data
    return np.sqrt(np.sum(error * error, 0))


def _find_closest_index(L, t):
    beginning, difference, best, end = 0, abs(L[0] - t), 0, len(L)
    while beginning < end:
        middle = int((end + beginning) / 2)
        if abs(L[middle] - t) < difference:
            difference = abs(L[middle] - t)
            best = middle
        if t == L[middle]:
            return middle
        elif L[middle] > t:
            end = middle
        else:
            beginning = middle + 1
    return best


def _ominus(a, b):
    return np.dot(np.linalg.inv(a), b)


def _tum_rpe(est, gt, index, delta):
    trans, rot = [], []
    for i in range(len(est)):
        j = _find_closest_index(index, index[i] + delta)
        if j == len(est) - 1:
            continue
        error44 = _ominus(_ominus(est[j], est[i]), _ominus(gt[j], gt[i]))
        trans.append(np.linalg.norm(error44[0:3, 3]))
        rot.append(np.arccos(min(1, max(-1, (np.trace(error44[0:3, 0:3]) - 1) / 2))))
    trans, rot = np.asarray(trans), np.degrees(np.asarray(rot))
    return np.sqrt(np.mean(trans**2)), np.sqrt(np.mean(rot**2)), len(trans)


# ------------------------------------------------------------------ hand-worked cases


def test_align_rigid_recovers_a_known_motion():
    src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]])
    T = _pose(_rot_z(30), (1.0, -2.0, 0.5))
    tgt = src @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(align_rigid(src, tgt), T, atol=1e-12)


def test_align_rigid_never_reflects():
    src = np.array([[1.0, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]])
    tgt = src * np.array([1.0, -1.0, 1.0])  # a mirror image: the best rotation, not the mirror
    assert np.linalg.det(align_rigid(src, tgt)[:3, :3]) == pytest.approx(1.0)


def test_ate_is_zero_for_a_rigidly_moved_trajectory():
    gt = _random_trajectory(20, seed=1)
    est = np.asarray([_pose(_rot_z(40), (3.0, 1.0, -2.0)) @ p for p in gt])
    result = absolute_trajectory_error(est, gt)
    assert result.rmse < 1e-9


def test_ate_by_hand_a_scaled_square():
    # centres on a square of half-side 1; the estimate 10 % larger: the best rigid alignment
    # is the identity (symmetry), each centre is 0.1 m off
    corners = [(1.0, 0, 0), (0, 1.0, 0), (-1.0, 0, 0), (0, -1.0, 0)]
    gt = np.asarray([_pose(t=c) for c in corners])
    est = np.asarray([_pose(t=np.asarray(c) * 1.1) for c in corners])
    result = absolute_trajectory_error(est, gt)
    assert result.rmse == pytest.approx(0.1)
    assert result.max == pytest.approx(0.1)
    np.testing.assert_allclose(result.T_gt_est, np.eye(4), atol=1e-12)


def test_rpe_by_hand_a_constant_overshoot():
    # truth moves 1 m along x per frame, the estimate 1.1 m: 0.1 m per frame; the pair that
    # ends on the last frame (and the last frame, clamped onto itself) is left out
    gt = np.asarray([_pose(t=(k, 0.0, 0.0)) for k in range(5)])
    est = np.asarray([_pose(t=(1.1 * k, 0.0, 0.0)) for k in range(5)])
    result = relative_pose_error(est, gt)
    assert result.num_pairs == 3
    assert result.translation_rmse == pytest.approx(0.1)
    assert result.rotation_rmse_deg == pytest.approx(0.0, abs=1e-6)
    assert result.unit == "frames"


def test_rpe_by_hand_a_rotation_drift():
    # the estimate turns 1 degree more per frame about the camera's own axis
    gt = np.asarray([_pose(_rot_z(10 * k)) for k in range(4)])
    est = np.asarray([_pose(_rot_z(11 * k)) for k in range(4)])
    result = relative_pose_error(est, gt)
    assert result.rotation_rmse_deg == pytest.approx(1.0)
    assert result.translation_rmse == pytest.approx(0.0, abs=1e-12)


def test_rpe_in_seconds_picks_the_closest_stamp():
    # stamps 0, 0.4, 0.9, 1.2, 2.0, 2.5: delta 1 s -> (0 -> 0.9), (0.4 -> 1.2), (0.9 -> 2.0);
    # 1.2 -> 2.0 as well; 2.0 and 2.5 end on the last frame
    stamps = np.array([0.0, 0.4, 0.9, 1.2, 2.0, 2.5])
    gt = np.asarray([_pose(t=(s, 0.0, 0.0)) for s in stamps])
    est = np.asarray([_pose(t=(2 * s, 0.0, 0.0)) for s in stamps])
    result = relative_pose_error(est, gt, stamps, delta=1.0)
    # errors: 0.9, 0.8, 1.1, 0.8
    assert result.num_pairs == 4
    assert result.translation_rmse == pytest.approx(math.sqrt((0.81 + 0.64 + 1.21 + 0.64) / 4))
    assert result.unit == "s"


# ------------------------------------------------------------------ against the TUM scripts


@pytest.mark.parametrize("seed", range(4))
def test_ate_matches_evaluate_ate(seed):
    gt = _random_trajectory(30, seed)
    noise = _random_trajectory(30, seed + 100)
    est = np.asarray(
        [_pose(_rot_z(25), (1.0, 2.0, 3.0)) @ g @ n for g, n in zip(gt, noise, strict=True)]
    )
    errors = _tum_align(est[:, :3, 3].T, gt[:, :3, 3].T)
    result = absolute_trajectory_error(est, gt)
    np.testing.assert_allclose(result.errors, errors, atol=1e-10)
    assert result.rmse == pytest.approx(np.sqrt(np.mean(errors**2)))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("delta", [1.0, 3.0])
def test_rpe_matches_evaluate_rpe(seed, delta):
    rng = np.random.default_rng(seed)
    gt = _random_trajectory(25, seed)
    est = np.asarray([g @ n for g, n in zip(gt, _random_trajectory(25, seed + 50), strict=True)])
    stamps = np.cumsum(rng.uniform(0.02, 0.1, size=25))
    for index, arg in ((stamps, stamps), (np.arange(25.0), None)):
        trans, rot, count = _tum_rpe(est, gt, list(index), delta * (0.3 if arg is not None else 1))
        result = relative_pose_error(est, gt, arg, delta * (0.3 if arg is not None else 1))
        assert result.num_pairs == count
        assert result.translation_rmse == pytest.approx(trans, rel=1e-9)
        assert result.rotation_rmse_deg == pytest.approx(rot, rel=1e-7, abs=1e-7)


# ------------------------------------------------------------------ bad input


def test_shape_errors():
    with pytest.raises(ShapeError):
        absolute_trajectory_error(np.zeros((3, 4, 4)), np.zeros((2, 4, 4)))
    with pytest.raises(ShapeError):
        absolute_trajectory_error(np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))
    with pytest.raises(ShapeError, match="increasing"):
        relative_pose_error(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1)), [0, 0, 1])
    with pytest.raises(ShapeError, match="delta"):
        relative_pose_error(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1)), delta=0)


def test_a_trajectory_shorter_than_delta_has_no_pairs():
    poses = np.tile(np.eye(4), (2, 1, 1))
    result = relative_pose_error(poses, poses, delta=5)
    assert result.num_pairs == 0 and math.isnan(result.translation_rmse)
