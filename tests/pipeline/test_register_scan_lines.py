"""Scan lines fixed to the sensor: an identity-like result of clouds sampled along lines gives
way to a second fit of what it leaves unexplained (`estimate_transform(scan_lines=True)`)."""

from __future__ import annotations

import math

import pytest
import torch

import byoc_cli.pipeline.register as register_module
from byoc_cli.pipeline.features import CloudFeatures
from byoc_cli.pipeline.register import RegisterConfig, estimate_transform, identity_like

#: 2 x this is the inlier threshold
VOXEL = 0.1


def _motion(deg: float, t=(0.0, 0.0, 0.0)) -> torch.Tensor:
    a = math.radians(deg)
    T = torch.eye(4, dtype=torch.float64)
    T[:2, :2] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    T[:3, 3] = torch.tensor(t, dtype=torch.float64)
    return T


def _cloud(points: torch.Tensor, feats: torch.Tensor) -> CloudFeatures:
    n = len(points)
    return CloudFeatures(points, feats, torch.arange(n), torch.zeros(n, 3, dtype=torch.int64))


def _scans(T_structure: torch.Tensor, pattern: int = 160, structure: int = 80, seed: int = 0):
    """Two scans in their sensors' frames: ``pattern`` points fixed to the sensor (the same in
    both: rings on the ground) and ``structure`` points of the scene, moved by
    ``T_structure (4, 4)`` in the second. Each point's feature is its own, shared by the two
    scans: the pattern matches itself, the structure matches the motion."""
    g = torch.Generator().manual_seed(seed)
    ground = torch.rand(pattern, 3, generator=g, dtype=torch.float64) * torch.tensor(
        [16.0, 16.0, 0.0], dtype=torch.float64
    ) - torch.tensor([8.0, 8.0, 1.8], dtype=torch.float64)
    boxes = torch.rand(structure, 3, generator=g, dtype=torch.float64) * torch.tensor(
        [6.0, 10.0, 4.0], dtype=torch.float64
    ) + torch.tensor([4.0, -5.0, -1.8], dtype=torch.float64)
    moved = boxes @ T_structure[:3, :3].T + T_structure[:3, 3]
    feats = torch.nn.functional.normalize(torch.randn(pattern + structure, 32, generator=g), dim=1)
    src = _cloud(torch.cat([ground, boxes]), feats)
    tgt = _cloud(torch.cat([ground, moved]), feats)
    return src, tgt


def _config(**changes) -> RegisterConfig:
    return RegisterConfig(
        **{"estimator": "ransac", "num_correspondences": 400, "max_points": 0, **changes}
    )


def test_identity_like_is_the_origin_staying_put_whatever_the_turn():
    assert identity_like(_motion(0.0), 0.2) and identity_like(_motion(90.0, (0.1, 0, 0)), 0.2)
    assert not identity_like(_motion(0.0, (0.0, 0.25, 0.0)), 0.2)
    assert not identity_like(_motion(0.0, (0.2, 0.0, 0.0)), 0.2)  # at the threshold: moved


def test_a_pattern_matched_to_itself_gives_way_to_the_motion_of_the_scene():
    truth = _motion(12.0, (4.0, 0.0, 0.0))
    src, tgt = _scans(truth)
    config = _config(min_confidence=0.0)
    plain = estimate_transform(src, tgt, config, VOXEL)
    assert torch.allclose(plain.T_tgt_src, torch.eye(4, dtype=torch.float64), atol=1e-6)
    assert "second_try" not in plain.timings  # not sampled along lines: never asked
    lines = estimate_transform(src, tgt, config, VOXEL, scan_lines=True)
    assert torch.allclose(lines.T_tgt_src, truth, atol=1e-6)
    assert lines.timings["second_try"] > 0
    # judged on every correspondence, as a first result is: the pattern's are its outliers
    assert lines.num_correspondences == plain.num_correspondences
    assert lines.num_inliers < plain.num_inliers


def test_a_sensor_that_did_not_move_keeps_the_identity():
    src, tgt = _scans(torch.eye(4, dtype=torch.float64))
    config = _config(min_confidence=0.0)
    plain = estimate_transform(src, tgt, config, VOXEL)
    lines = estimate_transform(src, tgt, config, VOXEL, scan_lines=True)
    assert torch.equal(lines.T_tgt_src, plain.T_tgt_src)  # nothing left to fit: no second
    assert lines.confidence == plain.confidence and "second_try" in lines.timings


def test_a_turn_in_place_is_identity_like_and_kept():
    # the sensor turned but did not move: the second motion leaves the origin where it is too
    src, tgt = _scans(_motion(30.0))
    lines = estimate_transform(src, tgt, _config(min_confidence=0.0), VOXEL, scan_lines=True)
    assert torch.allclose(lines.T_tgt_src, torch.eye(4, dtype=torch.float64), atol=1e-6)


def test_a_second_motion_below_the_gate_is_not_taken(monkeypatch):
    src, tgt = _scans(_motion(12.0, (4.0, 0.0, 0.0)))
    seen = []
    real = register_module._second_try

    def spy(*args, **kwargs):
        got = real(*args, **kwargs)
        seen.append(got)
        return got

    monkeypatch.setattr(register_module, "_second_try", spy)
    gated = estimate_transform(src, tgt, _config(min_confidence=1.0), VOXEL, scan_lines=True)
    assert seen == [None]
    assert torch.allclose(gated.T_tgt_src, torch.eye(4, dtype=torch.float64), atol=1e-6)


@pytest.mark.parametrize("refine", [None, "multiscale"])
def test_the_first_result_is_the_same_bytes_with_or_without_the_flag_when_it_moved(refine):
    truth = _motion(12.0, (4.0, 0.0, 0.0))
    src, tgt = _scans(truth, pattern=40, structure=200)  # the scene outnumbers the pattern
    config = _config(refine=refine)
    plain = estimate_transform(src, tgt, config, VOXEL)
    lines = estimate_transform(src, tgt, config, VOXEL, scan_lines=True)
    assert not identity_like(plain.T_tgt_src, 2 * VOXEL)
    assert lines.T_tgt_src.numpy().tobytes() == plain.T_tgt_src.numpy().tobytes()
    assert lines.confidence == plain.confidence and "second_try" not in lines.timings


def test_identity_like_is_measured_at_the_refinement_voxel():
    # a 10 cm motion: within the feature inlier threshold (20 cm), not within the
    # refinement's (4 cm at a 2 cm refinement voxel)
    src, tgt = _scans(_motion(0.0, (0.1, 0.0, 0.0)), pattern=0, structure=200)
    config = _config(min_confidence=0.0)
    fine = estimate_transform(src, tgt, config, VOXEL, refine_voxel=0.02, scan_lines=True)
    assert torch.allclose(fine.T_tgt_src, _motion(0.0, (0.1, 0.0, 0.0)), atol=1e-6)
    assert "second_try" not in fine.timings
    coarse = estimate_transform(src, tgt, config, VOXEL, scan_lines=True)
    assert "second_try" in coarse.timings  # asked, nothing left to fit: the result stays
    assert torch.equal(coarse.T_tgt_src, fine.T_tgt_src)
