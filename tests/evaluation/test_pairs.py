"""The eval-pairs runner: RGB-D test pairs, prepared pairs, known-transform recovery."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from byoc_cli.evaluation.methods import build_methods
from byoc_cli.evaluation.pairs import PairsConfig, evaluate_pairs, prepared_pairs, rgbd_pairs
from byoc_cli.geometry.transforms import axis_angle_to_matrix
from byoc_cli.io import write_ply, write_transform
from byoc_cli.io.rgbd import backproject, discover_sequences


def _box_surface(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = np.sign(pts[np.arange(n), axis])
    return pts * np.array([1.5, 1.0, 0.8])


def _prepared(tmp_path, transforms):
    for k, T in enumerate(transforms):
        folder = tmp_path / f"{k:04d}"
        folder.mkdir(parents=True)
        src = _box_surface(20000, k)
        write_ply(folder / "source.ply", src)
        write_ply(folder / "target.ply", src @ T[:3, :3].T + T[:3, 3])
        write_transform(folder / "T_gt.txt", T)
    return tmp_path


def _T(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = axis_angle_to_matrix(torch.tensor(rotvec, dtype=torch.float64)).numpy()
    T[:3, 3] = t
    return T


@pytest.mark.realdata
def test_rgbd_pairs_direction_and_spacing(shared_data):
    root = shared_data / "rgbd" / "tum_fr1_desk"
    pairs, described = rgbd_pairs([root], spacing=2)
    (seq,) = discover_sequences(root, require_poses=True)
    assert [p.name for p in pairs] == [
        f"tum_fr1_desk:{a}-{a + 2}" for a in range(0, len(seq) - 2, 2)
    ]
    assert described[0]["pairs"] == len(pairs) and described[0]["layout"] == "tum"
    first = pairs[0]
    np.testing.assert_allclose(first.T_gt, np.linalg.inv(seq.pose(0)) @ seq.pose(2))
    # the source is the later frame, read at full resolution
    points = first.source.load()
    depth = seq.read_depth(2)
    assert points.shape == ((depth > 0).sum(), 3)
    np.testing.assert_array_equal(points, backproject(depth, seq.K).points)
    assert len(rgbd_pairs([root], spacing=2, limit=1)[0]) == 1


@pytest.mark.realdata
def test_identity_errors_are_the_motion_and_icp_improves(shared_data):
    """Identity scores the pair's own motion; ICP from the identity lowers the error, which
    only happens when T_gt points the right way."""
    pairs, _ = rgbd_pairs([shared_data / "rgbd" / "tum_fr1_desk"], spacing=2, limit=3)
    methods = build_methods(["identity", "icp-plane"])
    result = evaluate_pairs(pairs, methods, PairsConfig())
    assert len(result.records) == 3
    for record in result.records:
        ident = record["methods"]["identity"]
        assert ident["rotation_error_deg"] == pytest.approx(record["gt_rotation_deg"])
        assert ident["translation_error_cm"] == pytest.approx(record["gt_translation_cm"])
        assert ident["chamfer"] > 0
    summary = result.summaries
    assert (
        summary["icp-plane"]["rotation_deg"]["mean"] < summary["identity"]["rotation_deg"]["mean"]
    )
    assert set(summary["identity"]["rotation_deg"]["accuracy_percent"]) == {"5", "10", "45"}
    assert set(summary["identity"]["translation_cm"]["accuracy_percent"]) == {"5", "10", "25"}
    assert set(summary["identity"]["chamfer"]["accuracy_percent"]) == {"1", "5", "10"}


def test_prepared_pairs_known_transform_recovery(tmp_path):
    transforms = [_T([0.0, 0.03, 0.01], [0.02, -0.01, 0.03]), _T([0.02, 0.0, -0.03], [0, 0.04, 0])]
    root = _prepared(tmp_path, transforms)
    pairs = prepared_pairs(root)
    assert [p.name for p in pairs] == ["0000", "0001"]
    methods = build_methods(["identity", "icp-point", "icp-plane"])
    result = evaluate_pairs(pairs, methods, PairsConfig())
    for record in result.records:
        for name in ("icp-point", "icp-plane"):
            out = record["methods"][name]
            assert out["rotation_error_deg"] < 0.3 and out["translation_error_cm"] < 0.5, name
            assert out["chamfer"] < record["methods"]["identity"]["chamfer"] / 10
    acc = result.summaries["icp-plane"]["rotation_deg"]["accuracy_percent"]
    assert acc == {"5": 100.0, "10": 100.0, "45": 100.0}
    assert result.summaries["identity"]["num_pairs"] == 2
    assert len(prepared_pairs(root, limit=1)) == 1


def test_feature_methods_and_cache(tmp_path):
    root = _prepared(tmp_path / "p", [_T([0.0, 0.2, 0.0], [0.1, 0.0, 0.0])])
    pairs = prepared_pairs(root)
    from byoc_cli.evaluation.cache import FeatureCache

    methods = build_methods(["fpfh-ransac", "fpfh-procrustes"])
    cache = FeatureCache(tmp_path / "cache")
    first = evaluate_pairs(pairs, methods, PairsConfig(), cache)
    assert (first.cache_hits, first.cache_misses) == (0, 2)  # one FPFH spec, two clouds
    out = first.records[0]["methods"]["fpfh-ransac"]
    assert out["rotation_error_deg"] < 2.0 and not out["failed"]
    second = evaluate_pairs(pairs, methods, PairsConfig(), FeatureCache(tmp_path / "cache"))
    assert (second.cache_hits, second.cache_misses) == (2, 0)
    assert second.records[0]["methods"]["fpfh-ransac"]["T_est"] == out["T_est"]


def test_multiscale_refinement_gets_the_full_clouds(tmp_path, monkeypatch):
    import dataclasses

    from byoc_cli.evaluation import methods as methods_module

    root = _prepared(tmp_path / "p", [_T([0.0, 0.2, 0.0], [0.1, 0.0, 0.0])])
    (plain,) = build_methods(["fpfh-ransac"])
    refined = dataclasses.replace(
        plain, name="refined", config=dataclasses.replace(plain.config, refine="multiscale")
    )
    assert refined.needs_clouds and not plain.needs_clouds
    assert refined.describe()["refine"] == "multiscale" and plain.describe()["refine"] == "none"
    (random_byoc,) = build_methods(["byoc-random"])
    assert random_byoc.needs_clouds  # the learned default refines, also for the random column
    seen = []
    real = methods_module.estimate_transform

    def spy(src, tgt, config, voxel_size, clouds=None):
        seen.append(None if clouds is None else (len(clouds[0]), len(clouds[1])))
        return real(src, tgt, config, voxel_size, clouds)

    monkeypatch.setattr(methods_module, "estimate_transform", spy)
    result = evaluate_pairs(prepared_pairs(root), [plain, refined], PairsConfig())
    assert seen == [None, (20000, 20000)]
    out = result.records[0]["methods"]
    assert out["refined"]["translation_error_cm"] < 0.5
    assert out["refined"]["translation_error_cm"] < out["fpfh-ransac"]["translation_error_cm"]
