"""Pose-graph helpers and FPFH starts (Open3D), and the pair refinement they serve."""

from __future__ import annotations

import math

import numpy as np
import pytest

from byoc_cli.pipeline.posegraph import (
    Edge,
    fpfh_ransac,
    multiscale_icp,
    optimize_pose_graph,
    prepare_cloud,
    prepared_fpfh_ransac,
)
from byoc_cli.pipeline.refine_pairs import pair_cloud, refine_pair
from byoc_cli.training.pseudo_poses import transform_difference


def _scene(seed: int = 0) -> np.ndarray:
    """Points on a floor, two walls and a few boxes: well constrained for ICP."""
    rng = np.random.default_rng(seed)
    parts = [
        np.c_[rng.uniform(0, 2, 6000), rng.uniform(0, 2, 6000), np.zeros(6000)],
        np.c_[np.zeros(4000), rng.uniform(0, 2, 4000), rng.uniform(0, 1.5, 4000)],
        np.c_[rng.uniform(0, 2, 4000), np.zeros(4000), rng.uniform(0, 1.5, 4000)],
    ]
    for cx, cy, s in ((0.6, 0.7, 0.3), (1.3, 1.2, 0.4), (1.5, 0.4, 0.2)):
        face = rng.uniform(-s / 2, s / 2, size=(1500, 3))
        axis = rng.integers(0, 3, 1500)
        face[np.arange(1500), axis] = np.sign(face[np.arange(1500), axis]) * s / 2
        parts.append(face + np.array([cx, cy, s / 2]))
    return np.concatenate(parts).astype(np.float64)


def _rigid(angle_deg: float, axis: list[float], t: list[float]) -> np.ndarray:
    axis_arr = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array(
        [
            [0, -axis_arr[2], axis_arr[1]],
            [axis_arr[2], 0, -axis_arr[0]],
            [-axis_arr[1], axis_arr[0], 0],
        ]
    )
    a = math.radians(angle_deg)
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K
    T[:3, 3] = t
    return T


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


#: the two pair ICPs: ``register-scans`` and ``odometry`` refine with ours, the self-posed
#: training pairs with Open3D's; (prepare, refine, global start of (prepared, points))
PAIR_ICPS = {
    "refine_pair": (
        pair_cloud,
        refine_pair,
        lambda prepared, points: fpfh_ransac(*points, 0.025, seed=0),
    ),
    "open3d": (
        prepare_cloud,
        multiscale_icp,
        lambda prepared, points: prepared_fpfh_ransac(*prepared, seed=0),
    ),
}


@pytest.mark.parametrize("kind", sorted(PAIR_ICPS))
def test_a_pair_icp_recovers_a_known_transform(kind):
    if kind == "open3d":
        pytest.importorskip("open3d")
    prepare, refine, _ = PAIR_ICPS[kind]
    tgt = _scene()
    T_tgt_src = _rigid(6.0, [0.3, 1, 0.2], [0.05, -0.04, 0.03])
    src = _apply(np.linalg.inv(T_tgt_src), _scene(1))
    est = refine(prepare(src, 0.025), prepare(tgt, 0.025), np.eye(4))
    rot, trans = transform_difference(T_tgt_src, est.T_tgt_src)
    assert rot < 0.5 and trans < 0.01
    assert est.fitness > 0.9 and est.rmse < 0.02
    assert est.information.shape == (6, 6)


@pytest.mark.parametrize("kind", sorted(PAIR_ICPS))
def test_fpfh_ransac_finds_a_large_motion(kind):
    pytest.importorskip("open3d")
    prepare, refine, start = PAIR_ICPS[kind]
    tgt = _scene()
    T_tgt_src = _rigid(60.0, [0, 0, 1], [0.3, 0.2, 0.0])
    src = _apply(np.linalg.inv(T_tgt_src), _scene(1))
    a, b = prepare(src, 0.025), prepare(tgt, 0.025)
    est = refine(a, b, start((a, b), (src, tgt)))
    rot, trans = transform_difference(T_tgt_src, est.T_tgt_src)
    assert rot < 1.0 and trans < 0.02


def test_pose_graph_prunes_a_wrong_loop_edge():
    pytest.importorskip("open3d")
    truth = [np.eye(4)]
    step = _rigid(5.0, [0, 0, 1], [0.1, 0.0, 0.0])
    for _ in range(5):
        truth.append(truth[-1] @ step)
    info = np.eye(6) * 1000.0
    rel = [np.linalg.inv(truth[k - 1]) @ truth[k] for k in range(1, 6)]
    edges = [Edge(k, k - 1, rel[k - 1], info, False) for k in range(1, 6)]
    good = Edge(5, 0, np.linalg.inv(truth[0]) @ truth[5], info, True)
    bad = Edge(4, 1, _rigid(40.0, [1, 0, 0], [0.5, 0.5, 0.0]), info, True)
    # start from a drifted chain
    drift = _rigid(1.0, [0, 1, 0], [0.01, 0.0, 0.0])
    start = [truth[0]] + [truth[k] @ np.linalg.matrix_power(drift, k) for k in range(1, 6)]
    poses, kept = optimize_pose_graph(start, [*edges, good, bad], 0.0375)
    assert kept[:5] == [True] * 5
    assert kept[5] and not kept[6]
    for pose, ref in zip(poses, truth, strict=True):
        rot, trans = transform_difference(ref, pose)
        assert rot < 0.5 and trans < 0.01
