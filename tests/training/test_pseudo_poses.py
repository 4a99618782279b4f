"""Self-posed pairs: verified relative poses from the tool's own registration."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from byoc_cli.training.pseudo_poses import (
    PseudoPoseConfig,
    estimate_pairs,
    pair_accuracy,
    pairs_from_json,
    pairs_to_json,
    rotation_angle_deg,
    transform_difference,
)


def test_rotation_angle_and_difference():
    a = math.radians(30.0)
    R = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    assert rotation_angle_deg(R) == pytest.approx(30.0)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [0.3, 0.4, 0.0]
    assert transform_difference(T, T) == pytest.approx((0.0, 0.0), abs=1e-6)
    rot, trans = transform_difference(np.eye(4), T)
    assert rot == pytest.approx(30.0) and trans == pytest.approx(0.5)


def test_config_validation():
    with pytest.raises(ValueError):
        PseudoPoseConfig(gaps=())
    with pytest.raises(ValueError):
        PseudoPoseConfig(voxel_size=0.0)


@pytest.mark.slow
@pytest.mark.realdata
def test_real_sequence_pairs_agree_with_ground_truth(shared_data):
    pytest.importorskip("open3d")
    from byoc_cli.io.rgbd import discover_sequences

    seq = discover_sequences(shared_data / "rgbd" / "tum_fr1_desk_full")[0]
    seq = dataclasses.replace(seq, frames=seq.frames[:33])
    config = PseudoPoseConfig(gaps=(4, 8), start_stride=4)
    result = estimate_pairs(seq, config)
    assert result.stats["breaks"] == 0
    assert len(result.pairs) >= 6
    assert all(p.i < p.j and p.fitness >= config.min_fitness for p in result.pairs)
    table = pair_accuracy(result, [seq.pose(i) for i in range(len(seq.frames))], config)
    for gap in (4, 8):
        assert table[gap]["kept"] >= 2
        # TUM's motion-capture poses and the best geometric fit of its depth differ by 1-4 deg
        # on this fast sequence (measured: ICP started AT the ground truth moves that far)
        assert table[gap]["median_rotation_deg"] < 5.0
        assert table[gap]["median_translation_cm"] < 5.0
    # every kept pair sits in the basin of ICP started from the ground truth
    from byoc_cli.pipeline.posegraph import multiscale_icp, prepare_cloud
    from byoc_cli.training.pseudo_poses import frame_points

    for pair in result.pairs[:4]:
        T_gt = np.linalg.inv(seq.pose(pair.i)) @ seq.pose(pair.j)
        clouds = [prepare_cloud(frame_points(seq, f), config.voxel_size) for f in (pair.j, pair.i)]
        from_gt = multiscale_icp(clouds[0], clouds[1], T_gt)
        rot, trans = transform_difference(from_gt.T_tgt_src, pair.T_i_j)
        assert rot < 0.5 and trans < 0.01
    # the cache record round-trips
    again = pairs_from_json(pairs_to_json(result, config, seq))
    assert [(p.i, p.j) for p in again] == [(p.i, p.j) for p in result.pairs]
    assert np.allclose(again[0].T_i_j, result.pairs[0].T_i_j, atol=1e-7)


class _Cloud:
    """Stands in for a prepared cloud: the finest level's points are all that is read."""

    def __init__(self, k: int) -> None:
        level = type("Level", (), {"points": np.full((4, 3), float(k))})()
        self.levels = [level]


def _motion(deg: float, metres: float) -> np.ndarray:
    a = math.radians(deg)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    T[0, 3] = metres
    return T


class _Icp:
    """ICP that converges to ``truth`` and fits (overlap 0.8) only when started within
    1 deg / 1 cm of it; elsewhere it stays put and fits badly (overlap 0.1)."""

    def __init__(self, truth: np.ndarray) -> None:
        self.truth = truth

    def __call__(self, src, tgt, T_init):
        from byoc_cli.pipeline.posegraph import PairEstimate

        rot, trans = transform_difference(self.truth, T_init)
        good = rot < 1.0 and trans < 0.01
        T = self.truth if good else np.asarray(T_init)
        return PairEstimate(T.copy(), 0.8 if good else 0.1, 0.01, np.eye(6))


def test_wide_pair_falls_back_to_the_global_start_under_the_same_checks(monkeypatch):
    import byoc_cli.training.pseudo_poses as pp

    truth = _motion(20.0, 0.3)
    icp = _Icp(truth)
    monkeypatch.setattr(pp, "_direct", lambda clouds, a, b, T: icp(clouds[b], clouds[a], T))
    clouds = [_Cloud(k) for k in range(6)]
    config = PseudoPoseConfig()
    calls = []

    def start(src, src_points, tgt, tgt_points):
        calls.append((src, tgt, src_points[0, 0], tgt_points[0, 0]))
        return truth

    chain_off = truth @ _motion(5.0, 0.05)  # within the chain bounds, outside ICP's basin
    est, origin = pp._wide_pair(clouds, 1, 5, chain_off, config, start)
    assert origin == "learned_start" and np.allclose(est.T_tgt_src, truth)
    assert calls == [(5, 1, 5.0, 1.0)]  # frame b onto frame a, with their points
    # a chain that fits: the global registration is not asked
    calls.clear()
    est, origin = pp._wide_pair(clouds, 1, 5, truth, config, start)
    assert origin == "chain" and not calls
    # no global start, or one that finds nothing: the chain's rejection stands
    assert pp._wide_pair(clouds, 1, 5, chain_off, config, None) == (None, "rejected_fit")
    none = lambda *_: None  # noqa: E731
    assert pp._wide_pair(clouds, 1, 5, chain_off, config, none) == (None, "rejected_fit")
    # a global estimate that fits but contradicts the chain (30 deg away) is not kept
    far = truth @ _motion(30.0, 0.0)
    assert pp._wide_pair(clouds, 1, 5, far, config, start) == (None, "rejected_fit")


def test_odometry_asks_the_global_start_instead_of_fpfh(monkeypatch):
    import byoc_cli.pipeline.posegraph as posegraph
    import byoc_cli.training.pseudo_poses as pp

    truth = _motion(12.0, 0.2)  # too far for ICP from the identity (in this stand-in)
    monkeypatch.setattr(posegraph, "multiscale_icp", _Icp(truth))

    def no_fpfh(*_a, **_k):
        raise AssertionError("FPFH was used although a global start was given")

    monkeypatch.setattr(posegraph, "fpfh_ransac", no_fpfh)
    clouds = [_Cloud(k) for k in range(3)]
    origin, est = pp._odometry_step(clouds, 2, np.eye(4), PseudoPoseConfig(), lambda *_: truth)
    assert origin == "learned" and est.fitness == 0.8
    # nothing found: the best ICP try is returned and fails the fit (a segment break)
    origin, est = pp._odometry_step(clouds, 2, np.eye(4), PseudoPoseConfig(), lambda *_: None)
    assert origin == "identity" and est.fitness == 0.1


@pytest.mark.realdata
def test_learned_start_registers_the_demo_pair_with_the_shipped_encoder(shared_data):
    from byoc_cli.io.matrix import read_transform
    from byoc_cli.io.pointcloud import read_point_cloud
    from byoc_cli.pipeline.default_weights import load_default_weights
    from byoc_cli.training.pseudo_poses import LearnedStart

    demo = shared_data / "pairs" / "3dmatch_demo"
    src = read_point_cloud(demo / "source.ply").points.astype(np.float64)
    tgt = read_point_cloud(demo / "target.ply").points.astype(np.float64)
    weights = load_default_weights()
    encoder = weights.encoder
    before = {k: v.clone() for k, v in encoder.state_dict().items()}
    encoder.train()
    start = LearnedStart(encoder, 0.025)
    T = start(7, src, 3, tgt)
    rot, trans = transform_difference(read_transform(demo / "T_gt.txt"), T)
    assert rot < 5.0 and trans < 0.1  # a start for ICP: RANSAC only, no refinement
    assert sorted(start.features) == [3, 7]  # each frame encoded once, by its index
    assert np.array_equal(start(7, src, 3, tgt), T)  # cached features, seeded RANSAC
    # the encoder handed in is untouched (a frozen copy is used; training mode kept)
    assert encoder.training
    assert all(torch.equal(v, before[k]) for k, v in encoder.state_dict().items())
    # too few points: no transform, not an exception
    assert start(8, src[:2], 3, tgt) is None
