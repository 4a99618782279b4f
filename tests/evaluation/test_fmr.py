"""The eval-fmr runner on synthetic benchmarks with known answers, pair selection, cache."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from byoc_cli.errors import DatasetError
from byoc_cli.evaluation.cache import FeatureCache
from byoc_cli.evaluation.fmr import (
    FmrConfig,
    evaluate_fmr,
    load_benchmark_pairs,
    pair_seed,
    sample_pair_subsets,
)
from byoc_cli.evaluation.methods import FeatureSpec, Method, build_methods
from byoc_cli.geometry import voxelize
from byoc_cli.io import write_ply
from byoc_cli.io.threedmatch import discover_benchmark
from byoc_cli.pipeline.features import CloudFeatures
from byoc_cli.pipeline.register import RegisterConfig
from tests.evaluation import _reference as ref


class OracleExtractor:
    """Features that are a smooth, distinctive function of the WORLD position of a point:
    random Fourier features of ``T_world_fragment x``. Matching is perfect where fragments
    overlap, so the expected FMR is known exactly."""

    name = "oracle"
    voxel_size = 0.05

    def __init__(self, poses: dict[str, np.ndarray]) -> None:
        self.poses = poses
        rng = np.random.default_rng(0)
        self.W = torch.from_numpy(rng.normal(scale=6.0, size=(3, 32)))
        self.b = torch.from_numpy(rng.uniform(0, 2 * np.pi, size=32))
        self.calls = 0

    def __call__(self, points: torch.Tensor, label: str = "cloud") -> CloudFeatures:
        self.calls += 1
        pose = torch.from_numpy(self.poses[Path(label).name])
        grid = voxelize(points, self.voxel_size)
        kept = points[grid.point_index].to(torch.float64)
        world = kept @ pose[:3, :3].T + pose[:3, 3]
        feats = torch.nn.functional.normalize(torch.cos(world @ self.W + self.b), dim=1).float()
        return CloudFeatures(kept, feats, grid.point_index, grid.coords)


def _box_surface(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = np.sign(pts[np.arange(n), axis])
    return pts * np.array([1.5, 1.0, 0.8])


def _transform(angle_deg: float, t) -> np.ndarray:
    from byoc_cli.geometry.transforms import axis_angle_to_matrix

    T = np.eye(4)
    axis = torch.tensor([0.2, 1.0, 0.3], dtype=torch.float64)
    axis = axis / axis.norm() * np.radians(angle_deg)
    T[:3, :3] = axis_angle_to_matrix(axis).numpy()
    T[:3, 3] = t
    return T


def _info(points: np.ndarray) -> np.ndarray:
    info = np.zeros((6, 6))
    for x, y, z in points:
        G = np.hstack([np.eye(3), -np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])])
        info += G.T @ G
    return info


def _matrix_lines(M: np.ndarray) -> str:
    return "".join(" ".join(f"{v:.12f}" for v in row) + "\n" for row in M)


def _make_benchmark(root: Path, wrong_scene_b: bool = True):
    """Scene ``a``: 3 fragments of one box seen from 3 poses, correct gt.log (pairs 0-1, 0-2,
    1-2). Scene ``b``: 2 fragments, gt.log claims a transform 2 m off (FMR must be 0).

    Returns ``poses`` for the oracle: fragment file name -> T_world_fragment.
    """
    world = _box_surface(3000, 0)
    poses = {}
    for scene, count in (("a", 3), ("b", 2)):
        frag_poses = [_transform(25 * k, [0.3 * k, -0.1 * k, 0.05]) for k in range(count)]
        log, info = "", ""
        for k, T_world_k in enumerate(frag_poses):
            points = (world - T_world_k[:3, 3]) @ T_world_k[:3, :3]  # world -> fragment k
            (root / scene).mkdir(parents=True, exist_ok=True)
            write_ply(root / scene / f"cloud_bin_{k}.ply", points)
            poses[f"{scene}/cloud_bin_{k}.ply"] = T_world_k
        for i in range(count):
            for j in range(i + 1, count):
                T_ij = np.linalg.inv(frag_poses[i]) @ frag_poses[j]  # maps j into i
                if scene == "b" and wrong_scene_b:
                    T_ij = T_ij.copy()
                    T_ij[:3, 3] += [2.0, 0.0, 0.0]
                log += f"{i}\t{j}\t{count}\n" + _matrix_lines(T_ij)
                pts_i = (world[:500] - frag_poses[i][:3, 3]) @ frag_poses[i][:3, :3]
                info += f"{i}\t{j}\t{count}\n" + _matrix_lines(_info(pts_i))
        (root / f"{scene}-evaluation").mkdir(parents=True)
        (root / f"{scene}-evaluation" / "gt.log").write_text(log)
        (root / f"{scene}-evaluation" / "gt.info").write_text(info)
    return poses


@pytest.fixture
def synthetic(tmp_path):
    root = tmp_path / "bench"
    poses = _make_benchmark(root)
    return root, poses


def _oracle_method(poses: dict[str, np.ndarray]) -> tuple[Method, OracleExtractor]:
    keyed = {}
    for name, pose in poses.items():
        keyed.setdefault(Path(name).name, pose)  # same world poses in both scenes
    extractor = OracleExtractor(keyed)
    spec = FeatureSpec("oracle", extractor, {"extractor": "oracle", "v": 1}, {})
    config = RegisterConfig(num_correspondences=200, max_points=5000, estimator="procrustes")
    return Method("oracle", "byoc", spec, config), extractor


def _untimed(records):
    return [
        {**r, "methods": {k: {**v, "seconds": 0} for k, v in r["methods"].items()}} for r in records
    ]


def test_pair_seed_and_subsets():
    assert pair_seed(0, "s", 1, 2) == pair_seed(0, "s", 1, 2) == ref.pair_seed(0, "s", 1, 2)
    assert len({pair_seed(0, "s", 1, 2), pair_seed(1, "s", 1, 2), pair_seed(0, "s", 2, 1)}) == 3
    src, tgt = sample_pair_subsets(10_000, 3000, 5000, 7)
    assert tgt is None and src.shape == (5000,)
    assert torch.equal(src, torch.sort(src).values)
    expected = ref.sample(10_000, 3000, 5000, 7)
    np.testing.assert_array_equal(src.numpy(), expected[0])


def test_known_fmr_per_scene_pooled_and_registration(synthetic):
    root, poses = synthetic
    method, _ = _oracle_method(poses)
    identity = build_methods(["identity"])[0]
    pair_set = load_benchmark_pairs(discover_benchmark(root))
    assert [(p.scene, p.i, p.j) for p in pair_set.pairs] == [
        ("a", 0, 1), ("a", 0, 2), ("a", 1, 2), ("b", 0, 1),
    ]  # fmt: skip
    result = evaluate_fmr(pair_set, [method, identity], FmrConfig(num_samples=1000))
    fmr = result.summaries["oracle"]["fmr"]
    assert fmr["per_scene"]["a"] == {"value": 1.0, "num_pairs": 3}
    assert fmr["per_scene"]["b"] == {"value": 0.0, "num_pairs": 1}
    assert fmr["mean_over_scenes"] == 0.5 and fmr["std_over_scenes"] == 0.5
    assert fmr["pooled"] == 0.75
    for record in result.records:
        feats = record["features"]["oracle"]
        if record["scene"] == "a":
            assert feats["inlier_ratio"] > 0.5 and feats["corr_inlier_ratio"] > 0.9
        else:
            assert feats["inlier_ratio"] == 0.0 and not feats["corr_recalled"]
    # registration: the oracle registers scene a exactly; scene b's ground truth is wrong
    rr = result.summaries["oracle"]["registration_recall"]
    assert rr["num_pairs"] == 1  # only (0, 2) has j - i > 1
    assert rr["pooled"] == 1.0
    rr_all = result.summaries["oracle"]["registration_recall_all_pairs"]
    assert rr_all["per_scene"] == {
        "a": {"value": 1.0, "num_pairs": 3},
        "b": {"value": 0.0, "num_pairs": 1},
    }
    assert result.summaries["identity"]["registration_recall_all_pairs"]["pooled"] == 0.0
    assert result.summaries["identity"]["fmr"] is None
    for record in result.records:
        ours = record["methods"]["oracle"]
        if record["scene"] == "a":
            assert ours["rotation_error_deg"] < 0.5 and ours["translation_error_m"] < 0.02


def test_limit_missing_fragments_and_cache(synthetic, tmp_path):
    root, poses = synthetic
    pair_set = load_benchmark_pairs(discover_benchmark(root), limit=1)
    assert [(p.scene, p.i, p.j) for p in pair_set.pairs] == [("a", 0, 1), ("b", 0, 1)]
    assert pair_set.num_listed == 4
    (root / "a" / "cloud_bin_2.ply").unlink()
    with pytest.raises(DatasetError) as info:
        load_benchmark_pairs(discover_benchmark(root))
    assert info.value.path.endswith("cloud_bin_2.ply")
    assert "gt.log line 6" in info.value.problem and "--allow-missing" in info.value.problem
    pair_set = load_benchmark_pairs(discover_benchmark(root), allow_missing=True)
    assert pair_set.skipped_pairs == [("a", 0, 2), ("a", 1, 2)]
    assert pair_set.missing_fragments == [str(root / "a" / "cloud_bin_2.ply")]
    # features are computed once per fragment and read back from the cache on a rerun
    method, extractor = _oracle_method(poses)
    cache_dir = tmp_path / "cache"
    first = evaluate_fmr(pair_set, [method], FmrConfig(num_samples=500), FeatureCache(cache_dir))
    assert (first.cache_hits, first.cache_misses, extractor.calls) == (0, 4, 4)
    assert len(list((cache_dir / "oracle").glob("*.npz"))) == 4
    second = evaluate_fmr(pair_set, [method], FmrConfig(num_samples=500), FeatureCache(cache_dir))
    assert (second.cache_hits, second.cache_misses, extractor.calls) == (4, 0, 4)
    assert _untimed(second.records) == _untimed(first.records)
    # a changed input file invalidates its entry
    shutil.copy(root / "b" / "cloud_bin_0.ply", root / "b" / "cloud_bin_1.ply")
    third = evaluate_fmr(pair_set, [method], FmrConfig(num_samples=500), FeatureCache(cache_dir))
    assert (third.cache_hits, third.cache_misses) == (3, 1)


def test_corrupt_cache_entry_is_recomputed(synthetic, tmp_path):
    root, poses = synthetic
    pair_set = load_benchmark_pairs(discover_benchmark(root), limit=1)
    method, _ = _oracle_method(poses)
    cache_dir = tmp_path / "cache"
    evaluate_fmr(pair_set, [method], FmrConfig(num_samples=200), FeatureCache(cache_dir))
    victim = sorted((cache_dir / "oracle").glob("*.npz"))[0]
    victim.write_bytes(b"not a zip")
    with pytest.warns(UserWarning, match="unusable feature cache entry"):
        again = evaluate_fmr(
            pair_set, [method], FmrConfig(num_samples=200), FeatureCache(cache_dir)
        )
    assert again.cache_misses == 1
    np.load(victim)  # rewritten
