"""RGB-D video readers (TUM, 3DMatch/7-Scenes/SUN3D, ScanNet, Redwood), pairs, preprocessing."""

from __future__ import annotations

import itertools
import json
import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from byoc_cli.errors import DatasetError, InputError, ShapeError
from byoc_cli.io.rgbd import (
    LAYOUTS,
    TUM_INTRINSICS,
    FrameError,
    Layout,
    RGBDFrame,
    RGBDSequence,
    SkippedFrame,
    backproject,
    discover_sequences,
    make_pairs,
    preprocess_frame,
    register_layout,
    registered_layouts,
    unregister_layout,
)

K_FR1 = np.array([[517.3, 0.0, 318.6], [0.0, 516.5, 255.3], [0.0, 0.0, 1.0]])
K_SMALL = np.array([[60.0, 0.0, 31.5], [0.0, 61.0, 24.0], [0.0, 0.0, 1.0]])


def _K(fx, fy, cx, cy):
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _save_depth(path, raw):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(raw, dtype=np.uint16)).save(path)


def _save_color(path, shape=(48, 64), value=None):
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = shape
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = (np.arange(w) * 255 // max(w - 1, 1))[None, :]
    rgb[..., 1] = (np.arange(h) * 255 // max(h - 1, 1))[:, None]
    rgb[..., 2] = 128 if value is None else value
    Image.fromarray(rgb).save(path)


def _raw_depth(shape=(48, 64), value=1500):
    raw = np.full(shape, value, np.uint16)
    raw[0, 0] = 0
    return raw


def _write_matrix(path, M):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(" ".join(f"{v:.17g}" for v in row) for row in np.asarray(M)) + "\n")


def _o3d_json(path, K, width=64, height=48):
    path.write_text(
        json.dumps(
            {"width": width, "height": height, "intrinsic_matrix": K.flatten(order="F").tolist()}
        )
    )


def _rot_z(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def _tum(folder, depth_stamps, rgb_stamps, gt=None, intrinsics=True):
    """A synthetic TUM sequence (64x48) with the given stamps."""
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# timestamp filename"]
    for t in depth_stamps:
        _save_depth(folder / "depth" / f"{t:.6f}.png", _raw_depth(value=5000))
        lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (folder / "depth.txt").write_text("\n".join(lines) + "\n")
    lines = ["# timestamp filename"]
    for t in rgb_stamps:
        _save_color(folder / "rgb" / f"{t:.6f}.png")
        lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(lines) + "\n")
    if gt is not None:
        (folder / "groundtruth.txt").write_text(
            "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(" ".join(map(str, r)) for r in gt)
        )
    if intrinsics:
        _o3d_json(folder / "intrinsics.json", K_SMALL)
    return folder


def _3dmatch_seq(folder, n=3, color_ext="png", raw=None):
    for k in range(n):
        stem = folder / f"frame-{k:06d}"
        _save_depth(stem.with_name(stem.name + ".depth.png"), _raw_depth() if raw is None else raw)
        _save_color(stem.with_name(f"{stem.name}.color.{color_ext}"))
        T = np.eye(4)
        T[:3, :3] = _rot_z(10 * k)
        T[:3, 3] = [0.1 * k, 0.0, 0.0]
        _write_matrix(stem.with_name(stem.name + ".pose.txt"), T)
    return folder


# ================================================================ real data


@pytest.mark.realdata
def test_tum_fr1_xyz(shared_data):
    folder = shared_data / "rgbd" / "tum_fr1_xyz"
    (seq,) = discover_sequences(folder)
    assert isinstance(seq, RGBDSequence) and seq.layout == "tum" and seq.name == "tum_fr1_xyz"
    assert len(seq.frames) == 10 and isinstance(seq.frames[0], RGBDFrame)
    assert seq.depth_scale == 5000.0 and seq.depth_shape == (480, 640)
    assert np.array_equal(seq.K, K_FR1)  # intrinsics.json, column-major
    stamps = [f.timestamp for f in seq.frames]
    assert stamps == sorted(stamps)
    # TUM associate.py (greedy, unique, < 0.02 s) leaves one depth without colour here
    assert sum(f.color_path is None for f in seq.frames) == 1 and not seq.has_color
    assert seq.num_skipped == 1 and "no depth" in seq.skipped[0].reason
    assert seq.has_poses
    depth = seq.read_depth(0)
    assert depth.dtype == np.float32 and depth.shape == (480, 640)
    valid = depth[depth > 0]
    assert valid.size > 0.5 * depth.size and 0.3 < valid.min() and valid.max() < 8.0
    color = seq.read_color(0)
    assert color.dtype == np.uint8 and color.shape == (480, 640, 3)
    raw = np.asarray(Image.open(seq.frames[0].depth_path)).astype(np.float32)
    assert np.allclose(depth, raw / 5000.0)

    with_color = discover_sequences(folder, require_color=True)[0]
    assert len(with_color.frames) == 9 and with_color.has_color and with_color.num_skipped == 2


@pytest.mark.realdata
def test_tum_pose_is_nearest_ground_truth(shared_data):
    folder = shared_data / "rgbd" / "tum_fr1_desk"
    (seq,) = discover_sequences(folder)
    assert len(seq.frames) == 9
    gt = np.loadtxt(folder / "groundtruth.txt", comments="#")
    for k, frame in enumerate(seq.frames):
        row = gt[np.argmin(np.abs(gt[:, 0] - frame.timestamp))]
        assert abs(row[0] - frame.timestamp) < 0.02
        pose = seq.pose(k)
        assert np.allclose(pose[:3, 3], row[1:4])
        R = pose[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1)
        # the rotation is the quaternion's: R v = q v q*
        x, y, z, w = row[4:8] / np.linalg.norm(row[4:8])
        v = np.array([0.3, -0.2, 0.9])
        u = np.array([x, y, z])
        qv = v + 2 * np.cross(u, np.cross(u, v) + w * v)
        assert np.allclose(R @ v, qv)


@pytest.mark.realdata
def test_tum_fr3_cabinet_keyframes(shared_data):
    folder = shared_data / "rgbd" / "tum_fr3_cabinet"
    (seq,) = discover_sequences(folder)
    assert len(seq.frames) == 58 and seq.num_skipped == 0
    assert seq.has_color and seq.has_poses
    fx, fy, cx, cy = TUM_INTRINSICS[3]
    assert np.array_equal(seq.K, _K(fx, fy, cx, cy))
    gt = np.loadtxt(folder / "groundtruth.txt", comments="#")
    assert np.allclose([f.pose[:3, 3] for f in seq.frames], gt[:, 1:4])  # same stamps
    assert seq.read_color(57).shape == (480, 640, 3)  # JPEG colour


@pytest.mark.realdata
def test_tum_fr1_rpy_723_rgb_722_depth(shared_data):
    (seq,) = discover_sequences(shared_data / "rgbd" / "tum_fr1_rpy")
    assert len(seq.frames) == 722  # one frame per depth image
    with_color = sum(f.color_path is not None for f in seq.frames)
    # every rgb image is either matched to one depth or recorded as skipped
    assert with_color + seq.num_skipped == 723
    assert len({f.color_path for f in seq.frames if f.color_path}) == with_color  # unique


@pytest.mark.realdata
def test_realsense_tabletop_3dmatch_layout(shared_data):
    folder = shared_data / "rgbd" / "realsense_tabletop"
    (seq,) = discover_sequences(folder)
    assert seq.layout == "3dmatch" and seq.name == "seq-01" and len(seq.frames) == 50
    assert seq.depth_scale == 1000.0 and seq.has_color and seq.has_poses
    assert seq.K[0, 0] == pytest.approx(615.1951904296875)
    assert seq.K[1, 2] == pytest.approx(247.51919555664062)
    numbers = [f.index for f in seq.frames]
    assert numbers == sorted(numbers) and numbers[0] == 15  # frame-000015 is the first
    assert np.array_equal(seq.pose(0), np.eye(4))
    depth = seq.read_depth(0)
    raw = np.asarray(Image.open(seq.frames[0].depth_path)).astype(np.float32)
    assert np.allclose(depth, raw / 1000.0)
    # the sequence folder itself, with the intrinsics one level up, works too
    (inner,) = discover_sequences(folder / "seq-01")
    assert inner.name == "seq-01" and np.array_equal(inner.K, seq.K)


def _check_first_cloud(seq, max_depth):
    """The first frame back-projects to a metric surface in front of the camera."""
    depth = seq.read_depth(0)
    points, pixel = backproject(depth, seq.K)
    assert depth.shape == seq.depth_shape and len(points) > 0.5 * depth.size
    z = points[:, 2]
    assert z.min() > 0.1 and 0.5 < np.median(z) < 3.0 and np.percentile(z, 95) < max_depth
    # horizontally adjacent pixels with depth are millimetres apart on a real surface
    # (about z / fx), not metres apart as with a wrong depth scale or intrinsics
    right = np.searchsorted(pixel, pixel + 1)
    right = np.minimum(right, len(pixel) - 1)
    adjacent = (pixel[right] == pixel + 1) & ((pixel + 1) % depth.shape[1] != 0)
    gaps = np.linalg.norm(points[right[adjacent]] - points[adjacent], axis=1)
    assert adjacent.sum() > 0.4 * depth.size and np.median(gaps) < 0.005


@pytest.mark.realdata
def test_tum_fr1_desk_full_depth_only_with_poses(shared_data):
    folder = shared_data / "rgbd" / "tum_fr1_desk_full"
    assert not (folder / "rgb.txt").exists()
    (seq,) = discover_sequences(folder)
    assert seq.layout == "tum" and seq.name == "tum_fr1_desk_full" and len(seq) == 298
    assert seq.num_skipped == 0 and not seq.has_color and seq.has_poses
    assert all(f.color_path is None for f in seq.frames)
    with pytest.raises(FrameError, match="no colour"):
        seq.read_color(0)
    assert seq.depth_scale == 5000.0 and seq.depth_shape == (480, 640)
    assert seq.intrinsics_source == str(folder / "intrinsics.json")
    assert np.allclose(seq.K, _K(*TUM_INTRINSICS[1]))
    stamps = np.array([f.timestamp for f in seq.frames])
    assert np.all(np.diff(stamps) > 0) and 0.05 < np.median(np.diff(stamps)) < 0.09  # ~15 Hz
    for i in (0, 150, 297):
        T = seq.pose(i)
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) and T[3, 3] == 1.0
    _check_first_cloud(seq, max_depth=4.0)
    with pytest.raises(DatasetError, match="colour"):
        discover_sequences(folder, require_color=True)


@pytest.mark.realdata
def test_realsense_office_redwood_depth_only_without_poses(shared_data):
    folder = shared_data / "rgbd" / "realsense_office"
    (seq,) = discover_sequences(folder)
    assert seq.layout == "redwood" and seq.name == "realsense_office" and len(seq) == 193
    assert seq.num_skipped == 0 and not seq.has_color and not seq.has_poses
    assert all(f.pose is None and f.color_path is None for f in seq.frames)
    assert [f.index for f in seq.frames] == list(range(193))
    assert seq.frames[-1].depth_path.name == "000192.png"
    assert seq.depth_scale == 1000.0 and seq.depth_shape == (480, 640)
    assert seq.intrinsics_source == str(folder / "intrinsic.json")
    assert np.array_equal(seq.K, _K(615.0, 615.0, 320.0, 240.0))
    raw = np.asarray(Image.open(seq.frames[0].depth_path)).astype(np.float32)
    assert np.allclose(seq.read_depth(0), raw / 1000.0)
    _check_first_cloud(seq, max_depth=12.0)
    with pytest.raises(DatasetError, match="poses"):
        discover_sequences(folder, require_poses=True)


@pytest.mark.realdata
def test_discover_all_real_sequences_sorted(shared_data):
    seqs = discover_sequences(shared_data / "rgbd")
    names = [s.name for s in seqs]
    assert names == [
        "realsense_office",
        "realsense_tabletop/seq-01",
        "tum_fr1_desk",
        "tum_fr1_desk_full",
        "tum_fr1_rpy",
        "tum_fr1_xyz",
        "tum_fr3_cabinet",
    ]
    assert [s.name for s in discover_sequences(shared_data / "rgbd")] == names  # deterministic


@pytest.mark.realdata
def test_real_frame_preprocessing_geometry(shared_data):
    (seq,) = discover_sequences(shared_data / "rgbd" / "tum_fr1_desk")
    depth, color = seq.read_depth(3), seq.read_color(3)
    d, c, K_new = preprocess_frame(depth, color, seq.K)
    assert d.shape == (128, 128) and c.shape == (128, 128, 3) and c.dtype == np.float32
    assert -1.0 <= c.min() and c.max() <= 1.0
    points, pixel = backproject(d, K_new)
    # each point, projected with the ORIGINAL intrinsics, falls inside the original pixel
    # whose depth it carries (nearest-neighbour resampling)
    uvw = points.astype(np.float64) @ seq.K.T
    u = np.floor(uvw[:, 0] / uvw[:, 2]).astype(int)
    v = np.floor(uvw[:, 1] / uvw[:, 2]).astype(int)
    assert np.allclose(depth[v, u], points[:, 2], rtol=1e-6)
    # and, with the new intrinsics, at its own pixel centre
    uvw = points.astype(np.float64) @ K_new.T
    assert np.allclose(uvw[:, 0] / uvw[:, 2], pixel % 128 + 0.5, atol=1e-3)
    assert np.allclose(uvw[:, 1] / uvw[:, 2], pixel // 128 + 0.5, atol=1e-3)


# ================================================================ TUM, synthetic


def test_tum_association_is_greedy_unique_within_limit(tmp_path):
    base = 1000.0
    depth = [base, base + 0.033, base + 0.066, base + 0.5]
    rgb = [base + 0.010, base + 0.040, base + 0.045, base + 0.3]
    (seq,) = discover_sequences(_tum(tmp_path / "seq", depth, rgb))
    colors = [None if f.color_path is None else f.color_path.stem for f in seq.frames]
    # closest pairs first: .033-.040, then .000-.010; .066-.045 is 0.021 s apart; .5 has none
    assert colors == [f"{base + 0.010:.6f}", f"{base + 0.040:.6f}", None, None]
    assert seq.num_skipped == 2  # rgb .045 and .3 unmatched
    (loose,) = discover_sequences(tmp_path / "seq", max_time_difference=0.05)
    assert loose.frames[2].color_path.stem == f"{base + 0.045:.6f}"


def test_tum_pose_association_and_tolerance(tmp_path):
    q = [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]  # 90 deg about z
    gt = [
        [10.000, 1.0, 2.0, 3.0, *q],
        [10.010, 9.0, 9.0, 9.0, 0.0, 0.0, 0.0, 1.0],
        [11.000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # zero quaternion: invalid
    ]
    folder = _tum(tmp_path / "s", [10.003, 10.5, 11.0], [10.003, 10.5, 11.0], gt=gt)
    (seq,) = discover_sequences(folder)
    T = seq.pose(0)  # nearest stamp 10.000
    assert np.allclose(T[:3, :3], _rot_z(90)) and np.allclose(T[:3, 3], [1, 2, 3])
    assert seq.pose(1) is None  # 0.49 s from any ground truth
    assert seq.pose(2) is None  # invalid quaternion
    assert not seq.has_poses
    (posed,) = discover_sequences(folder, require_poses=True)
    assert len(posed.frames) == 1 and posed.num_skipped == 2
    (tight,) = discover_sequences(folder, pose_time_tolerance=0.001)
    assert tight.pose(0) is None


def test_tum_intrinsics_from_folder_name_and_override(tmp_path):
    for n, name in [(1, "rgbd_dataset_freiburg1_xyz"), (2, "fr2_desk"), (3, "TUM-FR3-office")]:
        folder = _tum(tmp_path / name, [1.0], [1.0], intrinsics=False)
        (seq,) = discover_sequences(folder)
        assert np.array_equal(seq.K, _K(*TUM_INTRINSICS[n])), name
        assert seq.intrinsics_source == f"freiburg{n} (published)"
    _tum(tmp_path / "freiburg2" / "run_a", [1.0], [1.0], intrinsics=False)
    (seq,) = discover_sequences(tmp_path / "freiburg2")
    assert seq.name == "run_a" and np.array_equal(seq.K, _K(*TUM_INTRINSICS[2]))

    unnamed = _tum(tmp_path / "other" / "fr10_nope", [1.0], [1.0], intrinsics=False)
    with pytest.raises(DatasetError, match="without intrinsics") as info:
        discover_sequences(unnamed)
    assert info.value.path == str(unnamed)

    K = _K(100.0, 101.0, 30.0, 20.0)
    (seq,) = discover_sequences(unnamed, intrinsics=K)
    assert np.array_equal(seq.K, K) and seq.intrinsics_source == "override"
    path = tmp_path / "override.json"
    _o3d_json(path, K)
    (seq,) = discover_sequences(tmp_path / "fr2_desk", intrinsics=path)  # wins over the name
    assert np.array_equal(seq.K, K)
    txt = tmp_path / "K.txt"
    _write_matrix(txt, K)
    assert np.array_equal(discover_sequences(unnamed, intrinsics=txt)[0].K, K)
    with pytest.raises(ShapeError):
        discover_sequences(unnamed, intrinsics=np.eye(4))
    with pytest.raises(InputError, match="transposed"):
        discover_sequences(unnamed, intrinsics=K.T)
    with pytest.raises(InputError, match="no such file"):
        discover_sequences(unnamed, intrinsics=tmp_path / "missing.json")


def test_tum_json_column_major_and_size_check(tmp_path):
    folder = _tum(tmp_path / "s", [1.0], [1.0])
    (seq,) = discover_sequences(folder)
    assert np.array_equal(seq.K, K_SMALL) and seq.depth_shape == (48, 64)
    _o3d_json(folder / "intrinsics.json", K_SMALL, width=640, height=480)
    with pytest.raises(DatasetError, match="640x480 images") as info:
        discover_sequences(folder)
    assert info.value.path == str(folder / "intrinsics.json")


def test_tum_missing_and_corrupt_frames_are_skipped(tmp_path):
    folder = _tum(tmp_path / "s", [1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0])
    (folder / "depth" / f"{2.0:.6f}.png").unlink()  # listed but absent
    (folder / "depth" / f"{3.0:.6f}.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    (folder / "rgb" / f"{4.0:.6f}.png").unlink()
    with open(folder / "depth.txt", "a") as f:
        f.write("not-a-stamp depth/x.png\n")
    (seq,) = discover_sequences(folder)
    assert [f.timestamp for f in seq.frames] == [1.0, 3.0, 4.0]
    reasons = sorted(s.reason for s in seq.skipped)
    assert reasons == ["colour file not found", "depth file not found", "unparseable line"]
    assert seq.frames[2].color_path is None
    with pytest.raises(FrameError) as info:  # corrupt content: at read time, typed
        seq.read_depth(1)
    assert info.value.frame == 1 and info.value.path == str(seq.frames[1].depth_path)
    with pytest.raises(FrameError, match="no colour"):
        seq.read_color(2)

    (checked,) = discover_sequences(folder, verify=True)
    assert [f.timestamp for f in checked.frames] == [1.0, 4.0]
    assert checked.num_skipped == 4
    for i in range(len(checked.frames)):
        checked.read_depth(i)


def test_wrong_size_and_wrong_format_frames(tmp_path):
    folder = _tum(tmp_path / "s", [1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    _save_depth(folder / "depth" / f"{2.0:.6f}.png", _raw_depth((24, 32)))
    Image.fromarray(np.zeros((48, 64), np.uint8)).save(folder / "depth" / f"{3.0:.6f}.png")
    (seq,) = discover_sequences(folder)
    assert seq.read_depth(0).shape == (48, 64)
    with pytest.raises(FrameError, match="32x24"):
        seq.read_depth(1)
    with pytest.raises(FrameError, match="not a depth image"):
        seq.read_depth(2)
    (checked,) = discover_sequences(folder, verify=True)
    assert len(checked.frames) == 1 and checked.num_skipped == 2


def test_depth_only_tum(tmp_path):
    folder = _tum(tmp_path / "s", [1.0, 2.0], [])
    (folder / "rgb.txt").unlink()
    (seq,) = discover_sequences(folder)
    assert len(seq.frames) == 2 and not seq.has_color
    assert seq.read_depth(1).max() == pytest.approx(1.0)  # 5000 raw = 1 m
    with pytest.raises(DatasetError, match="with colour"):
        discover_sequences(folder, require_color=True)


# ================================================================ other layouts, synthetic


def test_7scenes_65535_invalid_and_sequences_per_scene(tmp_path):
    scene = tmp_path / "chess"
    _write_matrix(scene / "camera-intrinsics.txt", _K(585.0, 585.0, 320.0, 240.0))
    raw = _raw_depth(value=2000)
    raw[1, 1] = 65535
    _3dmatch_seq(scene / "seq-01", n=3, raw=raw)
    _3dmatch_seq(scene / "seq-02", n=2)
    seqs = discover_sequences(tmp_path)
    assert [s.name for s in seqs] == ["chess/seq-01", "chess/seq-02"]
    assert [len(s.frames) for s in seqs] == [3, 2]
    s = seqs[0]
    assert s.layout == "3dmatch" and s.K[0, 0] == 585.0 and s.depth_scale == 1000.0
    depth = s.read_depth(0)
    assert depth[1, 1] == 0.0 and depth[0, 0] == 0.0 and depth[2, 2] == pytest.approx(2.0)
    assert np.allclose(s.pose(2)[:3, :3], _rot_z(20)) and s.has_poses


def test_3dmatch_invalid_pose_and_missing_colour(tmp_path):
    scene = tmp_path / "scene"
    _write_matrix(scene / "camera-intrinsics.txt", K_SMALL)
    seq_dir = _3dmatch_seq(scene / "seq-01", n=4)
    (seq_dir / "frame-000001.pose.txt").write_text(
        "-inf -inf -inf -inf\n-inf -inf -inf -inf\n-inf -inf -inf -inf\n0 0 0 1\n"
    )
    (seq_dir / "frame-000002.pose.txt").write_text("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    (seq_dir / "frame-000003.pose.txt").unlink()
    (seq_dir / "frame-000003.color.png").unlink()
    (seq,) = discover_sequences(tmp_path)
    assert len(seq.frames) == 4
    assert [seq.pose(i) is None for i in range(4)] == [False, True, True, True]
    assert seq.frames[3].color_path is None and not seq.has_color
    (posed,) = discover_sequences(tmp_path, require_poses=True)
    assert [f.index for f in posed.frames] == [0] and posed.num_skipped == 3
    (colored,) = discover_sequences(tmp_path, require_color=True)
    assert [f.index for f in colored.frames] == [0, 1, 2]


def test_sun3d_jpg_colour(tmp_path):
    scene = tmp_path / "sun3d-home"
    _write_matrix(scene / "camera-intrinsics.txt", K_SMALL)
    _3dmatch_seq(scene / "seq-01", n=2, color_ext="jpg")
    (seq,) = discover_sequences(scene)
    assert seq.frames[0].color_path.suffix == ".jpg" and seq.has_color
    color = seq.read_color(1)
    assert color.shape == (48, 64, 3) and color.dtype == np.uint8


def test_scannet_uses_depth_intrinsics_and_resizes_colour(tmp_path):
    scene = tmp_path / "scans" / "scene0000_00"
    K_depth = _K(58.0, 58.5, 31.7, 24.1)
    _write_matrix(
        scene / "intrinsic" / "intrinsic_depth.txt",
        np.pad(K_depth, (0, 1)) + np.diag([0, 0, 0, 1.0]),
    )
    _write_matrix(
        scene / "intrinsic" / "intrinsic_color.txt",
        np.pad(_K(117.0, 117.0, 64.8, 48.4), (0, 1)) + np.diag([0, 0, 0, 1.0]),
    )
    for n in (0, 1, 2, 10):
        _save_depth(scene / "depth" / f"{n}.png", _raw_depth(value=1000 + n))
        _save_color(scene / "color" / f"{n}.jpg", shape=(97, 130))
        T = np.eye(4)
        T[:3, 3] = [n, 0, 0]
        _write_matrix(scene / "pose" / f"{n}.txt", T)
    _write_matrix(scene / "pose" / "2.txt", np.full((4, 4), -np.inf))
    (seq,) = discover_sequences(tmp_path)
    assert seq.layout == "scannet" and seq.name == "scans/scene0000_00"
    assert np.array_equal(seq.K, K_depth)
    assert [f.index for f in seq.frames] == [0, 1, 2, 10]  # numeric order
    assert seq.pose(2) is None and seq.pose(3)[0, 3] == 10.0
    assert seq.read_depth(3)[5, 5] == pytest.approx(1.010)
    color = seq.read_color(0)
    assert color.shape == (48, 64, 3)
    assert color[24, 0, 0] < 20 and color[24, -1, 0] > 235  # the ramp is resized, not cropped
    (scene / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"intrinsic_depth\.txt"):
        discover_sequences(tmp_path)


def test_redwood_by_stem_by_order_and_depth_only(tmp_path):
    a = tmp_path / "a"
    for k in range(3):
        _save_depth(a / "depth" / f"{k:06d}.png", _raw_depth())
        _save_color(a / "image" / f"{k:06d}.jpg")
    _o3d_json(a / "camera_intrinsic.json", K_SMALL)
    b = tmp_path / "b"  # Redwood object scans: stems differ, order matches
    for k, (ds, cs) in enumerate(
        [("0000001-000000000100", "0000001-000000000090")] * 1
        + [
            ("0000002-000000033400", "0000002-000000033390"),
            ("0000010-000000300000", "0000010-000000299990"),
        ]
    ):
        _save_depth(b / "depth" / f"{ds}.png", _raw_depth(value=1000 * (k + 1)))
        _save_color(b / "rgb" / f"{cs}.jpg")
    c = tmp_path / "c"  # depth only
    for k in (2, 10, 1):
        _save_depth(c / "depth" / f"{k}.png", _raw_depth())
    _o3d_json(tmp_path / "intrinsic.json", K_SMALL)  # shared by b and c
    seqs = discover_sequences(tmp_path)
    assert [s.name for s in seqs] == ["a", "b", "c"] and {s.layout for s in seqs} == {"redwood"}
    sa, sb, sc = seqs
    assert [f.color_path.name for f in sa.frames] == ["000000.jpg", "000001.jpg", "000002.jpg"]
    assert sb.frames[2].color_path.stem == "0000010-000000299990" and sb.has_color
    assert sb.read_depth(2)[3, 3] == pytest.approx(3.0)
    assert [f.depth_path.stem for f in sc.frames] == ["1", "2", "10"] and not sc.has_color
    assert [s.name for s in discover_sequences(tmp_path, require_color=True)] == ["a", "b"]


def test_no_sequence_folder_errors(tmp_path):
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("hi")
    with pytest.raises(DatasetError) as info:
        discover_sequences(tmp_path)
    assert info.value.path == str(tmp_path)
    assert "no RGB-D sequence found" in info.value.problem and "ScanNet" in info.value.problem
    with pytest.raises(DatasetError, match="does not exist"):
        discover_sequences(tmp_path / "missing")
    with pytest.raises(DatasetError, match="not a folder"):
        discover_sequences(tmp_path / "notes" / "readme.txt")
    empty = tmp_path / "empty_tum"
    empty.mkdir()
    (empty / "depth.txt").write_text("# nothing\n")
    _o3d_json(empty / "intrinsics.json", K_SMALL)
    with pytest.warns(UserWarning, match="without a usable frame"):
        with pytest.raises(DatasetError, match="no usable frame"):
            discover_sequences(empty)


def _toy_layout():
    """A layout of the test's own: ``toy.txt`` lists depth images, one per line."""

    def frames(folder, names, options):
        listed = (folder / "toy.txt").read_text().split()
        found = [RGBDFrame(k, folder / n, None, None, None) for k, n in enumerate(listed)]
        return [f for f in found if f.depth_path.is_file()], [
            SkippedFrame(f.depth_path.name, "depth file not found")
            for f in found
            if not f.depth_path.is_file()
        ]

    return Layout(
        name="toy",
        description="toy.txt",
        depth_scale=100.0,
        detect=lambda folder, names: "toy.txt" in names,
        frames=frames,
        intrinsics=lambda folder, root: (K_SMALL.copy(), (48, 64), "toy"),
    )


def test_a_registered_layout_is_discovered_before_redwood(tmp_path):
    folder = tmp_path / "data" / "t"
    _save_depth(folder / "depth" / "a.png", _raw_depth(value=150))
    (folder / "toy.txt").write_text("depth/a.png depth/gone.png\n")
    _o3d_json(folder / "intrinsic.json", K_SMALL)  # would also be a Redwood sequence
    assert [s.layout for s in discover_sequences(tmp_path / "data")] == ["redwood"]
    register_layout(_toy_layout(), before="redwood")
    try:
        assert [x.name for x in registered_layouts()] == [
            "tum",
            "3dmatch",
            "scannet",
            "toy",
            "redwood",
        ]
        (seq,) = discover_sequences(tmp_path / "data")
        assert seq.layout == "toy" and seq.name == "t" and seq.depth_scale == 100.0
        assert len(seq) == 1 and seq.skipped == [SkippedFrame("gone.png", "depth file not found")]
        assert seq.read_depth(0)[1, 1] == pytest.approx(1.5)
        with pytest.raises(ValueError, match="registered already"):
            register_layout(_toy_layout())
        with pytest.raises(DatasetError, match=r"looked for .*toy\.txt"):
            discover_sequences(tmp_path / "data" / "t" / "depth")
    finally:
        unregister_layout("toy")
    assert [x.name for x in registered_layouts()] == list(LAYOUTS)
    with pytest.raises(ValueError, match="no registered"):
        register_layout(_toy_layout(), before="nope")
    with pytest.raises(ValueError, match="no registered"):
        unregister_layout("toy")


def test_depth_scale_override(tmp_path):
    folder = _tum(tmp_path / "s", [1.0], [1.0])
    (seq,) = discover_sequences(folder, depth_scale=1000.0)
    assert seq.depth_scale == 1000.0 and seq.read_depth(0).max() == pytest.approx(5.0)
    with pytest.raises(ValueError):
        discover_sequences(folder, depth_scale=0.0)


def test_symlinked_sequences_are_visited_once(tmp_path):
    folder = _tum(tmp_path / "data" / "s", [1.0], [1.0])
    (tmp_path / "data" / "link").symlink_to(folder, target_is_directory=True)
    (tmp_path / "data" / "s" / "loop").symlink_to(tmp_path / "data", target_is_directory=True)
    seqs = discover_sequences(tmp_path / "data")
    assert len(seqs) == 1


def test_sequence_pickles(tmp_path):
    import pickle

    (seq,) = discover_sequences(_tum(tmp_path / "s", [1.0], [1.0]))
    back = pickle.loads(pickle.dumps(seq))
    assert np.array_equal(back.read_depth(0), seq.read_depth(0))


# ================================================================ pairs


def test_pairs_train_and_val():
    assert make_pairs(25, spacing=20, mode="train") == [(i, i + 20) for i in range(5)]
    assert make_pairs(61, spacing=20, mode="val") == [(0, 20), (20, 40), (40, 60)]
    assert make_pairs(60, spacing=20, mode="val") == [(0, 20), (20, 40)]
    assert make_pairs(20, spacing=20) == [] and make_pairs(0) == []
    with pytest.raises(ValueError):
        make_pairs(10, spacing=0)
    with pytest.raises(ValueError):
        make_pairs(10, mode="test")
    with pytest.raises(ValueError):
        make_pairs(-1)


@given(st.integers(0, 300), st.integers(1, 40))
def test_pairs_properties(n, spacing):
    train = make_pairs(n, spacing, "train")
    val = make_pairs(n, spacing, "val")
    assert len(train) == max(0, n - spacing)
    assert set(val) <= set(train)
    assert all(j - i == spacing and 0 <= i and j < n for i, j in train + val)
    assert all(i % spacing == 0 for i, _ in val)
    assert all(b[0] == a[1] for a, b in itertools.pairwise(val))  # consecutive


# ================================================================ preprocessing


def test_preprocess_intrinsics_landscape_and_portrait():
    depth = np.ones((480, 640), np.float32)
    _, _, K_new = preprocess_frame(depth, None, K_FR1)
    s = 128 / 480
    assert np.allclose(K_new, _K(517.3 * s, 516.5 * s, (318.6 - 80) * s, 255.3 * s))
    _, _, K_new = preprocess_frame(np.ones((640, 480), np.float32), None, K_FR1)
    assert np.allclose(K_new, _K(517.3 * s, 516.5 * s, 318.6 * s, (255.3 - 80) * s))


@settings(max_examples=40, deadline=None)
@given(
    st.integers(8, 90),
    st.integers(8, 90),
    st.integers(4, 64),
    st.floats(20.0, 300.0),
    st.integers(0, 2**31 - 1),
)
def test_preprocess_preserves_geometry(h, w, size, f, seed):
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.5, 4.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.2] = 0.0
    K = _K(f, f * 1.01, w / 2 + 1.3, h / 2 - 0.7)
    d, c, K_new = preprocess_frame(depth, None, K, size=size)
    assert d.shape == (size, size) and d.dtype == np.float32 and c is None
    points, pixel = backproject(d, K_new)
    # own pixel centre with K_new
    uvw = points.astype(np.float64) @ K_new.T
    assert np.allclose(uvw[:, 0] / uvw[:, 2], pixel % size + 0.5, atol=1e-3)
    assert np.allclose(uvw[:, 1] / uvw[:, 2], pixel // size + 0.5, atol=1e-3)
    # the same 3-D point as the original pixel it was sampled from: projected with the
    # original K it falls inside that pixel (float64 rays: output pixel centres can land
    # exactly on an original pixel's left/top edge, which belongs to that pixel)
    z = d.reshape(-1)[pixel].astype(np.float64)
    rays = np.stack([pixel % size + 0.5, pixel // size + 0.5, np.ones_like(z)], axis=1)
    uvw = (rays @ np.linalg.inv(K_new).T * z[:, None]) @ K.T
    u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    ui = np.clip(np.floor(u + 1e-9).astype(int), 0, w - 1)
    vi = np.clip(np.floor(v + 1e-9).astype(int), 0, h - 1)
    assert np.all(np.abs(u - (ui + 0.5)) <= 0.5 + 1e-6)
    assert np.all(np.abs(v - (vi + 0.5)) <= 0.5 + 1e-6)
    assert np.array_equal(depth[vi, ui], d.reshape(-1)[pixel])
    assert np.allclose(points, (rays @ np.linalg.inv(K_new).T) * z[:, None], rtol=1e-6)
    assert np.count_nonzero(d) == len(points)


def test_preprocess_colour_aligned_with_depth():
    h, w = 60, 100
    depth = np.ones((h, w), np.float32)
    color = np.zeros((h, w, 3), np.uint8)
    color[..., 0] = (np.arange(w) * 2)[None, :]  # red = 2 u
    color[..., 1] = (np.arange(h) * 4)[:, None]  # green = 4 v
    K = _K(50.0, 50.0, 50.0, 30.0)
    _, c, _ = preprocess_frame(depth, color, K, size=30)
    assert c.shape == (30, 30, 3) and c.dtype == np.float32
    raw = (c + 1.0) * 127.5
    # output pixel u' covers original columns [20 + 2u', 20 + 2u' + 2): mean of red = 2u + 1
    u_src = 20 + 2 * np.arange(30) + 0.5
    assert np.allclose(raw[10, 1:-1, 0], 2 * u_src[1:-1], atol=1.0)
    v_src = 2 * np.arange(30) + 0.5
    assert np.allclose(raw[1:-1, 10, 1], 4 * v_src[1:-1], atol=1.5)
    assert c.min() >= -1.0 and c.max() <= 1.0


def test_preprocess_and_backproject_errors():
    with pytest.raises(ShapeError):
        preprocess_frame(np.ones((4, 4, 1)), None, np.eye(3))
    with pytest.raises(ShapeError):
        preprocess_frame(np.ones((4, 4)), np.zeros((4, 5, 3), np.uint8), np.eye(3))
    with pytest.raises(ShapeError):
        preprocess_frame(np.ones((4, 4)), np.zeros((4, 4, 3), np.float32), np.eye(3))
    with pytest.raises(ShapeError):
        preprocess_frame(np.ones((4, 4)), None, np.eye(4))
    with pytest.raises(ValueError):
        preprocess_frame(np.ones((4, 4)), None, np.eye(3), size=0)
    with pytest.raises(ShapeError):
        backproject(np.ones(4), np.eye(3))
    with pytest.raises(ValueError):
        backproject(np.ones((4, 4)), np.zeros((3, 3)))


def test_backproject_pixel_centres_and_drops_invalid():
    depth = np.array([[2.0, 0.0, np.nan], [1.0, -1.0, 4.0]], np.float32)
    K = _K(2.0, 4.0, 1.0, 1.0)
    points, pixel = backproject(depth, K)
    assert points.dtype == np.float32 and pixel.dtype == np.int64
    assert pixel.tolist() == [0, 3, 5]
    expected = [
        [2.0 * (0.5 - 1) / 2, 2.0 * (0.5 - 1) / 4, 2.0],
        [1.0 * (0.5 - 1) / 2, 1.0 * (1.5 - 1) / 4, 1.0],
        [4.0 * (2.5 - 1) / 2, 4.0 * (1.5 - 1) / 4, 4.0],
    ]
    assert np.allclose(points, expected)
    empty_points, empty_pixel = backproject(np.zeros((3, 3), np.float32), K)
    assert empty_points.shape == (0, 3) and empty_pixel.shape == (0,)


def test_copied_real_tum_without_intrinsics_uses_name(shared_data, tmp_path):
    src = shared_data / "rgbd" / "tum_fr1_xyz"
    dst = tmp_path / "rgbd_dataset_freiburg1_xyz"
    dst.mkdir()
    for name in ("rgb.txt", "depth.txt"):
        shutil.copy(src / name, dst / name)
    (dst / "rgb").symlink_to(src / "rgb", target_is_directory=True)
    (dst / "depth").symlink_to(src / "depth", target_is_directory=True)
    (seq,) = discover_sequences(dst)
    assert np.array_equal(seq.K, K_FR1) and not seq.has_poses
    assert seq.read_depth(0).shape == (480, 640)


# ================================================================ one depth image's layout


def test_the_layout_of_a_single_depth_image(tmp_path):
    from byoc_cli.io.rgbd.registry import layout_of_depth_image

    tum = _tum(tmp_path / "tum", [1.0, 2.0], [1.0])
    image = next((tum / "depth").iterdir())
    layout, folder = layout_of_depth_image(image)
    assert (layout.name, layout.depth_scale, folder) == ("tum", 5000.0, tum.absolute())
    _3dmatch_seq(tmp_path / "scene" / "seq-01", n=2)
    frame = tmp_path / "scene" / "seq-01" / "frame-000000.depth.png"
    assert layout_of_depth_image(frame)[0].name == "3dmatch"
    loose = tmp_path / "loose"
    loose.mkdir()
    _save_depth(loose / "d.png", _raw_depth())
    assert layout_of_depth_image(loose / "d.png") is None
