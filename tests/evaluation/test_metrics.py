"""Evaluation metrics on hand-made cases and against brute-force references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.evaluation.metrics import (
    CHAMFER_SCALE,
    accuracy_at,
    chamfer_distance,
    correspondence_inlier_ratio,
    error_summary,
    fused_chamfer,
    nn_inlier_ratio,
    pose_errors,
    quaternion_from_rotation,
    recall_by_group,
    registration_rmse,
)
from byoc_cli.geometry.transforms import axis_angle_to_matrix, make_transform
from tests.evaluation import _reference as ref


def _rot(axis, angle_deg) -> torch.Tensor:
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    return axis_angle_to_matrix(axis * math.radians(angle_deg))


def _skew(p):
    x, y, z = p
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])


def _info(points: np.ndarray) -> np.ndarray:
    """An information matrix as gt.info builds it: sum of [I, -skew(p)]^T [I, -skew(p)]."""
    info = np.zeros((6, 6))
    for p in points:
        G = np.hstack([np.eye(3), -_skew(p)])
        info += G.T @ G
    return info


# ================================================================== quaternions, RMSE


@pytest.mark.parametrize(
    ("axis", "angle"),
    [((1, 0, 0), 30), ((0, 1, 0), 179), ((0, 0, 1), 178), ((1, 0, 0), 179.5), ((1, 2, 3), 90)],
)
def test_quaternion_of_known_rotations(axis, angle):
    q = quaternion_from_rotation(_rot(axis, angle))
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    half = math.radians(angle) / 2
    np.testing.assert_allclose(q.numpy(), [math.cos(half), *(math.sin(half) * u)], atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4))
def test_quaternion_matches_the_eigenvector_method(values):
    q = np.asarray(values)
    if np.linalg.norm(q) < 1e-3:
        return
    w, x, y, z = q / np.linalg.norm(q)
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    ours = quaternion_from_rotation(torch.from_numpy(R)).numpy()
    theirs = ref.quaternion(R)
    assert ours[0] >= 0
    if ours[0] > 1e-6:  # at w = 0, q and -q are both canonical
        np.testing.assert_allclose(ours, theirs, atol=1e-7)


def test_rmse_is_the_correspondence_rmse_of_the_quadratic_form():
    """p^T info p / N = mean |t + q_xyz x p|^2 exactly, for info built from the points p."""
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3)) + np.array([0.0, 0.0, 2.0])
    info = _info(points)
    assert info[0, 0] == 50
    T_gt = make_transform(_rot((0.3, 1, 0.2), 40), torch.tensor([0.5, -1.0, 2.0])).numpy()
    E = make_transform(_rot((1, -1, 0.5), 3), torch.tensor([0.02, 0.05, -0.01])).numpy()
    T_est = T_gt @ E
    q = quaternion_from_rotation(torch.from_numpy(E))[1:].numpy()
    expected = math.sqrt(np.mean(np.sum((E[:3, 3] + np.cross(q, points)) ** 2, axis=1)))
    assert registration_rmse(T_est, T_gt, info) == pytest.approx(expected, rel=1e-9)
    assert registration_rmse(T_gt, T_gt, info) == pytest.approx(0.0, abs=1e-12)
    assert registration_rmse(T_est, T_gt, info) == pytest.approx(ref.rmse(T_est, T_gt, info))


def test_rmse_of_a_pure_translation_and_degenerate_info():
    info = _info(np.random.default_rng(1).normal(size=(20, 3)))
    T = np.eye(4)
    T_est = np.eye(4)
    T_est[:3, 3] = [0.3, 0.0, 0.4]
    assert registration_rmse(T_est, T, info) == pytest.approx(0.5)
    assert math.isnan(registration_rmse(T_est, T, np.zeros((6, 6))))
    with pytest.raises(ShapeError):
        registration_rmse(T_est, T, np.eye(5))


@pytest.mark.realdata
def test_official_rmse_on_real_ground_truth(shared_data):
    """The library's RMSE equals the independent reference on the real gt.info records."""
    folder = shared_data / "3dmatch" / "benchmarks" / "3DMatch" / "7-scenes-redkitchen"
    logs = ref.parse_blocks(folder / "gt.log", 4)
    infos = ref.parse_blocks(folder / "gt.info", 6)
    rng = np.random.default_rng(2)
    for key in list(logs)[:40]:
        E = make_transform(
            axis_angle_to_matrix(torch.from_numpy(rng.normal(size=3) * 0.05)),
            torch.from_numpy(rng.normal(size=3) * 0.1),
        ).numpy()
        T_est = logs[key] @ E
        ours = registration_rmse(T_est, logs[key], infos[key])
        assert ours == pytest.approx(ref.rmse(T_est, logs[key], infos[key]), rel=1e-9)


# ================================================================== matching metrics


def test_nn_inlier_ratio_hand_made():
    points = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    feats = torch.eye(4)
    T = make_transform(_rot((0, 0, 1), 90), torch.tensor([0.0, 0.0, 0.5]))
    moved = points @ T[:3, :3].T + T[:3, 3]
    # identical features: every match is the true point
    assert nn_inlier_ratio(points, feats, moved, feats, T).inlier_ratio == 1.0
    # swap the features of two target points: those two matches go wrong
    swapped = feats[[1, 0, 2, 3]]
    out = nn_inlier_ratio(points, feats, moved, swapped, T, tau1=0.1)
    assert (out.inlier_ratio, out.num_matches, out.num_inliers) == (0.5, 4, 2)
    # a tau1 larger than the error makes them inliers again
    assert nn_inlier_ratio(points, feats, moved, swapped, T, tau1=1.5).inlier_ratio == 1.0
    # wrong ground truth (the inverse): only points on the rotation axis survive
    inv = torch.linalg.inv(T)
    assert nn_inlier_ratio(points, feats, moved, feats, inv).inlier_ratio == 0.0


def test_nn_inlier_ratio_queries_from_the_smaller_set():
    rng = np.random.default_rng(3)
    points = torch.from_numpy(rng.uniform(size=(30, 3)))
    feats = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(30, 8))).float(), dim=1)
    T = torch.eye(4, dtype=torch.float64)
    out = nn_inlier_ratio(points[:10], feats[:10], points, feats, T)
    assert (out.num_matches, out.inlier_ratio) == (10, 1.0)
    out = nn_inlier_ratio(points, feats, points[:12], feats[:12], T)
    assert (out.num_matches, out.inlier_ratio) == (12, 1.0)
    assert nn_inlier_ratio(points[:0], feats[:0], points, feats, T) == (0.0, 0, 0)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.integers(5, 60), st.integers(5, 60))
def test_nn_inlier_ratio_matches_brute_force(seed, n, m):
    rng = np.random.default_rng(seed)
    ps, pt = rng.uniform(size=(n, 3)), rng.uniform(size=(m, 3))
    fs = rng.normal(size=(n, 6)).astype(np.float32)
    ft = rng.normal(size=(m, 6)).astype(np.float32)
    fs /= np.linalg.norm(fs, axis=1, keepdims=True)
    ft /= np.linalg.norm(ft, axis=1, keepdims=True)
    T = make_transform(_rot((1, 1, 0), 10), torch.tensor([0.1, 0, 0])).numpy()
    out = nn_inlier_ratio(
        torch.from_numpy(ps),
        torch.from_numpy(fs),
        torch.from_numpy(pt),
        torch.from_numpy(ft),
        torch.from_numpy(T),
        tau1=0.3,
    )
    lo, hi, count = ref.nn_inlier_bounds(ps, fs, pt, ft, T, 0.3)
    assert out.num_matches == count
    assert lo <= out.num_inliers <= hi


def test_correspondence_inlier_ratio():
    p = torch.zeros(4, 3, dtype=torch.float64)
    q = torch.tensor([[0.0, 0, 0], [0.05, 0, 0], [0.2, 0, 0], [0, 0.0999, 0]])
    assert correspondence_inlier_ratio(p, q, torch.eye(4)) == 0.75
    assert correspondence_inlier_ratio(p[:0], q[:0], torch.eye(4)) == 0.0
    with pytest.raises(ShapeError):
        correspondence_inlier_ratio(p, q[:3], torch.eye(4))


def test_recall_by_group_fcgf_and_pooled():
    flags = [True, False, True, True, False, False]
    groups = ["a", "a", "a", "a", "b", "b"]
    out = recall_by_group(flags, groups)
    assert out.per_group == {"a": (0.75, 4), "b": (0.0, 2)}
    assert out.mean == 0.375 and out.std == 0.375  # population std over the two scenes
    assert out.pooled == 0.5 and out.num_pairs == 6
    values = recall_by_group(flags, groups, values=[0.1, 0.2, 0.3, 0.4, 0.5, 0.7])
    assert values.per_group["b"] == (pytest.approx(0.6), 2)
    empty = recall_by_group([], [])
    assert math.isnan(empty.mean) and math.isnan(empty.pooled)
    with pytest.raises(ValueError):
        recall_by_group([True], ["a", "b"])


def test_accuracy_and_error_summary():
    assert accuracy_at([1.0, 5.0, 9.9, 10.0, float("nan")], [5, 10]) == {5.0: 20.0, 10.0: 60.0}
    s = error_summary([1.0, 2.0, 4.0, float("inf")], [3.0])
    assert s.accuracy == {3.0: 50.0} and s.num_pairs == 4
    assert s.mean == pytest.approx(7 / 3) and s.median == 2.0
    assert math.isnan(error_summary([], [1.0]).accuracy[1.0])


def test_pose_errors():
    T_gt = make_transform(_rot((0, 1, 0), 20), torch.tensor([1.0, 0, 0]))
    T_est = make_transform(_rot((0, 1, 0), 27), torch.tensor([1.0, 0.3, 0.4]))
    rot, trans = pose_errors(T_est, T_gt)
    assert rot == pytest.approx(7.0) and trans == pytest.approx(0.5)


# ================================================================== chamfer


def test_chamfer_hand_made_and_brute_force():
    a = np.zeros((1, 3))
    b = np.array([[0.0, 0.0, 0.1]])
    assert chamfer_distance(a, b) == pytest.approx(CHAMFER_SCALE * 2 * 0.01)
    rng = np.random.default_rng(4)
    x, y = rng.uniform(size=(200, 3)), rng.uniform(size=(150, 3))
    D = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    expected = CHAMFER_SCALE * (D.min(1).mean() + D.min(0).mean())
    assert chamfer_distance(x, y) == pytest.approx(expected, rel=1e-9)
    assert chamfer_distance(x, x) == 0.0
    with pytest.raises(ShapeError):
        chamfer_distance(x[:0], y)


def test_fused_chamfer_is_zero_for_the_true_pose_and_grows_with_error():
    rng = np.random.default_rng(5)
    src, tgt = rng.uniform(size=(300, 3)), rng.uniform(size=(300, 3))
    T_gt = make_transform(_rot((0, 0, 1), 10), torch.tensor([0.1, 0, 0])).numpy()
    assert fused_chamfer(src, tgt, T_gt, T_gt) == 0.0
    errors = []
    for shift in (0.01, 0.05, 0.2):
        T = T_gt.copy()
        T[:3, 3] += [shift, 0, 0]
        errors.append(fused_chamfer(src, tgt, T, T_gt))
    assert 0 < errors[0] < errors[1] < errors[2]
