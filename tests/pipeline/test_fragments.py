"""Fragment benchmarks: TSDF fusion against exact synthetic renders, ground truth, real data."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from byoc_cli.errors import DatasetError, InputError, ShapeError, require_open3d
from byoc_cli.evaluation.fmr import load_benchmark_pairs
from byoc_cli.evaluation.metrics import registration_rmse
from byoc_cli.io import read_gt_info, read_gt_log, read_gt_overlap, read_point_cloud
from byoc_cli.io.rgbd import FrameError, backproject, discover_sequences
from byoc_cli.io.threedmatch import discover_benchmark
from byoc_cli.pipeline.fragments import (
    fragment_overlap,
    fragment_windows,
    fuse_fragment,
    information_matrix,
    make_fragment_benchmark,
    relative_pose,
)
from tests.pipeline import _synthetic as syn

VOXEL = 0.01
SDF_TRUNC = 0.04
NUM_FRAMES = 20


def _to_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return points.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """20 exact renders on a 57 deg arc around the block, as a 3DMatch RGB-D sequence."""
    poses = syn.orbit_poses(NUM_FRAMES)
    root = syn.write_sequence(tmp_path_factory.mktemp("synthetic") / "room", poses)
    return {"root": root, "poses": poses, "sequence": discover_sequences(root)[0]}


@pytest.fixture(scope="module")
def made(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "bench"
    result = make_fragment_benchmark(
        scene["sequence"], out, scene="room", frames_per_fragment=5,
        voxel_size=VOXEL, sdf_trunc=SDF_TRUNC, min_overlap=0.3,
    )  # fmt: skip
    return {"out": out, "result": result}


# ================================================================== small pieces


def test_fragment_windows_by_hand():
    assert fragment_windows(10, 5) == [range(0, 5), range(5, 10)]
    assert fragment_windows(11, 5) == [range(0, 5), range(5, 10)]  # the tail is dropped
    assert fragment_windows(10, 4, stride=3) == [range(0, 4), range(3, 7), range(6, 10)]
    assert fragment_windows(4, 5) == []
    with pytest.raises(ValueError):
        fragment_windows(10, 0)
    with pytest.raises(ValueError):
        fragment_windows(10, 5, stride=0)


def test_relative_pose_maps_source_camera_into_target_camera():
    rng = np.random.default_rng(0)
    poses = syn.orbit_poses(6)
    poses[:, :3, 3] += rng.normal(size=(6, 3))
    T = relative_pose(poses[1], poses[5])
    point_src = rng.normal(size=3)
    world = poses[5][:3, :3] @ point_src + poses[5][:3, 3]
    expected = poses[1][:3, :3].T @ (world - poses[1][:3, 3])
    np.testing.assert_allclose(T[:3, :3] @ point_src + T[:3, 3], expected, atol=1e-12)
    with pytest.raises(ShapeError):
        relative_pose(np.eye(3), np.eye(4))


# ================================================================== fusion


def test_fused_fragment_lies_on_the_true_surfaces(scene):
    """Exact renders: the fused points, taken to the world by the first pose, lie on the room
    and block surfaces (TSDF zero crossings at 1 cm voxels: median error ~1 mm)."""
    points = fuse_fragment(
        scene["sequence"], range(10), scene["poses"][:10], voxel_size=VOXEL, sdf_trunc=SDF_TRUNC
    )
    assert points.dtype == np.float32 and points.shape[1] == 3 and len(points) > 20_000
    error = syn.surface_distance(_to_world(points, scene["poses"][0]))
    assert np.median(error) < 0.003
    assert np.percentile(error, 99) < 1.5 * VOXEL
    # the block is in it: points on its top face
    top = (np.abs(_to_world(points, scene["poses"][0])[:, 1] - syn.BLOCK[1][1]) < 0.005).sum()
    assert top > 500


def test_fusion_depends_only_on_relative_poses(scene):
    """Moving every pose by one rigid transform of the world changes nothing; poses are the
    caller's (here the ground truth), not read from the sequence."""
    poses = scene["poses"][:6]
    world = relative_pose(syn.look_at(np.array([3.0, -1.0, 2.0]), np.zeros(3)), np.eye(4))
    a = fuse_fragment(scene["sequence"], range(6), poses, voxel_size=VOXEL, sdf_trunc=SDF_TRUNC)
    b = fuse_fragment(
        scene["sequence"], range(6), world @ poses, voxel_size=VOXEL, sdf_trunc=SDF_TRUNC
    )
    assert abs(len(a) - len(b)) <= 0.01 * len(a)
    assert fragment_overlap(a, b, np.eye(4), voxel_size=0.01, radius=0.005) > 0.98


def test_fusion_with_wrong_poses_is_not_on_the_surfaces(scene):
    """The poses passed are used: 5 cm of noise on the translations of frames 1-5 (frame 0
    exact) takes the fused points off the surfaces."""
    poses = scene["poses"][:6].copy()
    poses[1:, :3, 3] += np.random.default_rng(0).normal(scale=0.05, size=(5, 3))
    points = fuse_fragment(
        scene["sequence"], range(6), poses, voxel_size=VOXEL, sdf_trunc=SDF_TRUNC
    )
    error = syn.surface_distance(_to_world(points, poses[0]))
    assert np.median(error) > 0.006


def test_min_observations_counts_frames(scene):
    seq, poses = scene["sequence"], scene["poses"]
    assert len(fuse_fragment(seq, [0], poses[:1], voxel_size=0.02, sdf_trunc=0.06,
                             min_observations=1)) > 0  # fmt: skip
    assert len(fuse_fragment(seq, [0, 1], poses[:2], voxel_size=0.02, sdf_trunc=0.06,
                             min_observations=3)) == 0  # fmt: skip


@pytest.mark.parametrize(
    ("kwargs", "error"),
    [
        ({"frame_indices": []}, ShapeError),
        ({"frame_indices": [0, 99]}, ShapeError),
        ({"poses_world_cam": np.eye(4)[None].repeat(3, 0)}, ShapeError),
        ({"poses_world_cam": np.full((2, 4, 4), np.nan)}, ShapeError),
        ({"poses_world_cam": np.stack([np.eye(4), 2 * np.eye(4)])}, ShapeError),
        ({"sdf_trunc": 0.005}, ValueError),
        ({"voxel_size": 0.0}, ValueError),
        ({"min_observations": 0}, ValueError),
    ],
)
def test_fuse_fragment_rejects_bad_arguments(scene, kwargs, error):
    args = {"frame_indices": [0, 1], "poses_world_cam": scene["poses"][:2], "voxel_size": 0.01}
    args.update(kwargs)
    with pytest.raises(error):
        fuse_fragment(scene["sequence"], **args)


# ================================================================== the benchmark


def test_benchmark_layout_and_gt_log_against_the_generating_poses(scene, made):
    out, result = made["out"], made["result"]
    poses = scene["poses"]
    assert [f.frames for f in result.fragments] == [tuple(range(s, s + 5)) for s in (0, 5, 10, 15)]
    assert sorted(p.name for p in out.iterdir()) == [
        "make-fragments.json",
        "room",
        "room-evaluation",
    ]
    assert sorted(p.name for p in (out / "room-evaluation").iterdir()) == [
        "gt.info", "gt.log", "gt_overlap.log",
    ]  # fmt: skip
    records = read_gt_log(out / "room-evaluation" / "gt.log")
    assert records and all(r.i < r.j and r.num_fragments == 4 for r in records)
    assert [(r.i, r.j) for r in records] == [(p.i, p.j) for p in result.pairs]
    for r in records:
        # the generator's poses, not the reader's: T_i_j = inv(pose of frame 5i) @ pose of 5j
        expected = np.linalg.inv(poses[5 * r.i]) @ poses[5 * r.j]
        np.testing.assert_allclose(r.T_tgt_src, expected, atol=1e-9)
        # the ground truth really superposes the fragments
        tgt = read_point_cloud(out / "room" / f"cloud_bin_{r.i}.ply").points
        src = read_point_cloud(out / "room" / f"cloud_bin_{r.j}.ply").points
        moved = _to_world(src, r.T_tgt_src)
        assert fragment_overlap(tgt, moved, np.eye(4)) > 0.3
        error = syn.surface_distance(_to_world(moved, poses[5 * r.i]))
        assert np.median(error) < 0.003
    overlaps = read_gt_overlap(out / "room-evaluation" / "gt_overlap.log")
    assert set(overlaps) == {(r.i, r.j) for r in records}
    assert all(0.3 < v <= 1.0 for v in overlaps.values())
    manifest = json.loads((out / "make-fragments.json").read_text())
    assert [f["frames"] for f in manifest["fragments"]] == [[0, 4], [5, 9], [10, 14], [15, 19]]
    np.testing.assert_allclose(manifest["fragments"][2]["T_world_cam"], poses[10], atol=1e-12)


def test_fragments_are_binary_float32_xyz_plys_in_the_first_camera_frame(scene, made):
    path = made["out"] / "room" / "cloud_bin_1.ply"
    header = path.read_bytes()[:300].split(b"end_header")[0].decode()
    assert "binary_little_endian" in header
    assert [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")] == list(
        "xyz"
    )
    assert "property float x" in header
    points = read_point_cloud(path).points
    error = syn.surface_distance(_to_world(points, scene["poses"][5]))
    assert np.median(error) < 0.003


def test_gt_info_convention_in_the_official_rmse(made):
    """info[0, 0] = N and the top-left block N * I, so an estimate off by a pure 10 cm
    translation has an official RMSE of exactly 10 cm; the ground truth itself 0."""
    out = made["out"]
    infos = read_gt_info(out / "room-evaluation" / "gt.info")
    records = read_gt_log(out / "room-evaluation" / "gt.log")
    assert [(r.i, r.j) for r in infos] == [(r.i, r.j) for r in records]
    for rec, inf in zip(records, infos, strict=True):
        info = inf.info
        n = info[0, 0]
        assert 0 < n <= 5000
        np.testing.assert_allclose(info[:3, :3], n * np.eye(3), atol=1e-9 * n)
        np.testing.assert_allclose(info, info.T, atol=1e-9 * np.abs(info).max())
        assert registration_rmse(rec.T_tgt_src, rec.T_tgt_src, info) == pytest.approx(0, abs=1e-9)
        shifted = rec.T_tgt_src.copy()
        shifted[:3, 3] += rec.T_tgt_src[:3, :3] @ np.array([0.06, 0.0, 0.08])
        assert registration_rmse(shifted, rec.T_tgt_src, info) == pytest.approx(0.1, rel=1e-6)


def test_benchmark_is_read_by_the_evaluation(made):
    scenes = discover_benchmark(made["out"])
    assert [s.name for s in scenes] == ["room"] and scenes[0].gt_info is not None
    pairs = load_benchmark_pairs(scenes)
    assert len(pairs.pairs) == len(made["result"].pairs)
    assert all(p.info is not None and p.overlap is not None for p in pairs.pairs)


def test_a_stride_makes_overlapping_windows(scene, tmp_path):
    result = make_fragment_benchmark(
        scene["sequence"], tmp_path / "b", scene="room", frames_per_fragment=8, stride=4,
        voxel_size=0.02, sdf_trunc=0.06,
    )  # fmt: skip
    assert [f.frames[0] for f in result.fragments] == [0, 4, 8, 12]
    assert (0, 1) in [(p.i, p.j) for p in result.pairs]


@pytest.mark.parametrize(("low", "high"), [(0.3, 0.3), (0.3, 0.1), (0.1, 1.5)])
def test_an_empty_overlap_band_is_refused_before_any_work(scene, tmp_path, low, high):
    with pytest.raises(ValueError, match="max_overlap must lie in"):
        make_fragment_benchmark(
            scene["sequence"], tmp_path / "b", scene="room", frames_per_fragment=5,
            min_overlap=low, max_overlap=high,
        )  # fmt: skip
    assert not (tmp_path / "b").exists()


def test_nonempty_out_dir_is_refused_and_left_alone(scene, tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        make_fragment_benchmark(scene["sequence"], out, scene="room", frames_per_fragment=5)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_an_empty_out_dir_is_used(scene, tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    make_fragment_benchmark(
        scene["sequence"], out, scene="room", frames_per_fragment=10, voxel_size=0.02,
        sdf_trunc=0.06,
    )  # fmt: skip
    assert (out / "room" / "cloud_bin_1.ply").is_file()


def test_a_corrupt_frame_leaves_nothing_written(scene, tmp_path):
    """Frame 12 (third fragment) is garbage: the error names it, and neither the output nor a
    staging folder remains."""
    root = syn.write_sequence(tmp_path / "room", scene["poses"][:15])
    (root / "seq-01" / "frame-000012.depth.png").write_bytes(b"not a png")
    sequence = discover_sequences(root)[0]
    out = tmp_path / "out"
    with pytest.raises(FrameError, match="frame-000012"):
        make_fragment_benchmark(sequence, out, scene="room", frames_per_fragment=5,
                                voxel_size=0.02, sdf_trunc=0.06)  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == ["room"]


def test_frames_without_pose_and_short_sequences_are_refused(scene, tmp_path):
    sequence = scene["sequence"]
    unposed = dataclasses.replace(sequence, frames=[f._replace(pose=None) for f in sequence.frames])
    with pytest.raises(DatasetError, match="no pose"):
        make_fragment_benchmark(unposed, tmp_path / "a", scene="room", frames_per_fragment=5)
    with pytest.raises(DatasetError, match="fewer than one fragment"):
        make_fragment_benchmark(sequence, tmp_path / "b", scene="room", frames_per_fragment=50)
    with pytest.raises(ValueError, match="scene name"):
        make_fragment_benchmark(sequence, tmp_path / "c", scene="a/b", frames_per_fragment=5)
    assert not any(tmp_path.iterdir())


def test_depth_beyond_the_truncation_gives_an_error_not_an_empty_fragment(scene, tmp_path):
    with pytest.raises(DatasetError, match="has no point"):
        make_fragment_benchmark(scene["sequence"], tmp_path / "out", scene="room",
                                frames_per_fragment=5, depth_trunc=0.2)  # fmt: skip
    assert not any(tmp_path.iterdir())


# ================================================================== real data

SAMPLE = "3dmatch/sample"
KITCHEN = "7-scenes-redkitchen"


def _sample(shared_data: Path):
    root = shared_data / SAMPLE
    logs = {}
    for suite in ("3DMatch", "3DLoMatch"):
        for r in read_gt_log(root / suite / f"{KITCHEN}-evaluation" / "gt.log"):
            logs[(r.i, r.j)] = (suite, r.T_tgt_src)
    clouds = {
        k: read_point_cloud(root / "3DMatch" / KITCHEN / f"cloud_bin_{k}.ply").points
        for k in (0, 4, 7, 21, 34)
    }
    return logs, clouds


@pytest.mark.realdata
@pytest.mark.parametrize("pair", [(0, 4), (4, 7)])
def test_information_matrix_matches_the_official_gt_info(shared_data, pair):
    """The real fragments 0, 4, 7 (full density) with their gt.log: our gt.info of the pair has
    the official structure (translation first, N * I, A = [I | -[p]x] in fragment i's frame)
    and entries within 3 % of the official file's largest entry."""
    logs, clouds = _sample(shared_data)
    official = {
        (r.i, r.j): r.info
        for r in read_gt_info(shared_data / "3dmatch/benchmarks/3DMatch" / KITCHEN / "gt.info")
    }[pair]
    i, j = pair
    info = information_matrix(clouds[i], clouds[j], logs[pair][1])
    assert info[0, 0] == official[0, 0] == 5000
    np.testing.assert_allclose(info[:3, :3], 5000 * np.eye(3), atol=1e-6)
    np.testing.assert_allclose(np.diag(info[:3, 3:]), 0, atol=1e-6)
    assert np.array_equal(np.sign(np.round(info[:3, 3:])), np.sign(np.round(official[:3, 3:])))
    assert np.abs(info - official).max() < 0.03 * np.abs(official).max()


@pytest.mark.realdata
def test_overlap_separates_the_3dmatch_and_3dlomatch_sample_pairs(shared_data):
    """The sample's 3DMatch pairs (> 30 % overlap by the benchmark's makers) measure above
    0.3, its 3DLoMatch pairs (10-30 %) below."""
    logs, clouds = _sample(shared_data)
    for (i, j), (suite, T) in logs.items():
        overlap = fragment_overlap(clouds[i], clouds[j], T)
        assert (overlap > 0.3) == (suite == "3DMatch"), (i, j, suite, overlap)


@pytest.mark.realdata
def test_a_real_fragment_is_the_same_array_on_every_run(shared_data):
    """Open3D's hash map hands the TSDF points out in an order that changes between runs (a
    register-scans test failed in CI on it): the fragment comes out sorted, the same bytes."""
    sequence = discover_sequences(shared_data / "rgbd" / "tum_fr1_desk_full")[0]
    poses = np.stack([sequence.pose(k) for k in range(15)])
    runs = [fuse_fragment(sequence, range(15), poses) for _ in range(3)]
    assert len(runs[0]) > 50_000
    for points in runs[1:]:
        np.testing.assert_array_equal(points, runs[0])
    assert (np.diff(runs[0][:, 0]) >= 0).all()


@pytest.mark.realdata
def test_real_tum_fragment_agrees_with_its_frames(shared_data, tmp_path):
    """First 20 frames of fr1_desk (15 Hz) at the 3DMatch recipe, 10 frames per fragment: the
    raw depth of each fragment's first frame lies on the fragment (median < 1.5 cm), and
    gt.log holds the ground-truth relative pose of the two first frames."""
    sequence = discover_sequences(shared_data / "rgbd" / "tum_fr1_desk_full")[0]
    sequence = dataclasses.replace(sequence, frames=sequence.frames[:20])
    result = make_fragment_benchmark(
        sequence, tmp_path / "out", scene="desk", frames_per_fragment=10
    )
    assert len(result.fragments) == 2 and all(f.num_points > 50_000 for f in result.fragments)
    assert [(p.i, p.j) for p in result.pairs] == [(0, 1)]
    (record,) = read_gt_log(tmp_path / "out" / "desk-evaluation" / "gt.log")
    expected = np.linalg.inv(sequence.pose(0)) @ sequence.pose(10)
    np.testing.assert_allclose(record.T_tgt_src, expected, atol=1e-9)
    for fragment in result.fragments:
        points = read_point_cloud(tmp_path / "out" / "desk" / f"cloud_bin_{fragment.index}.ply")
        frame = backproject(sequence.read_depth(fragment.frames[0]), sequence.K).points
        frame = frame[frame[:, 2] < 3.0].astype(np.float64)
        o3d = require_open3d()
        distance = np.asarray(
            o3d.geometry.PointCloud(o3d.utility.Vector3dVector(frame)).compute_point_cloud_distance(
                o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.points.astype(float)))
            )
        )
        assert np.median(distance) < 0.015, np.median(distance)


def test_synthetic_depth_pngs_hold_the_rendered_depth(tmp_path):
    """The synthetic writer's PNGs are what the reader expects (guards the helper itself)."""
    poses = syn.orbit_poses(2)
    root = syn.write_sequence(tmp_path / "r", poses)
    depth = np.asarray(Image.open(root / "seq-01" / "frame-000000.depth.png"))
    np.testing.assert_allclose(depth / 1000.0, syn.render_depth(poses[0]), atol=6e-4)
