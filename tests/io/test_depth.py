"""Depth images and intrinsics: reading, back-projection at pixel centres, real RGB-D frames."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from byoc_cli.errors import DependencyError, InputError, ShapeError, require_open3d
from byoc_cli.io import (
    Intrinsics,
    LoadedCloud,
    depth_to_points,
    read_depth_cloud,
    read_depth_image,
    read_intrinsics,
)

K_FR1 = np.array([[517.3, 0.0, 318.6], [0.0, 516.5, 255.3], [0.0, 0.0, 1.0]])


def _error(func, path, *args, **kwargs):
    with pytest.raises(InputError) as info:
        func(*args, **kwargs)
    assert info.value.path == str(path)
    assert str(info.value).startswith(f"{path}: ")
    return info.value.problem


def _save_depth16(path, raw):
    Image.fromarray(np.asarray(raw, dtype=np.uint16)).save(path)


def _first_depth(folder, pattern):
    frames = sorted(folder.glob(pattern))
    assert frames, f"no {pattern} in {folder}"
    return frames[0]


# ---------------------------------------------------------------- intrinsics


def test_open3d_json_is_column_major(shared_data):
    intr = read_intrinsics(shared_data / "rgbd" / "tum_fr1_xyz" / "intrinsics.json")
    assert isinstance(intr, Intrinsics)
    assert (intr.width, intr.height) == (640, 480)
    fx, fy, cx, cy = intr.K[0, 0], intr.K[1, 1], intr.K[0, 2], intr.K[1, 2]
    assert (fx, fy, cx, cy) == (517.3, 516.5, 318.6, 255.3)  # the published fr1 values
    assert np.array_equal(intr.K, K_FR1)


def test_json_written_by_open3d(tmp_path):
    try:
        o3d = require_open3d()
    except DependencyError as exc:
        pytest.skip(str(exc))
    camera = o3d.camera.PinholeCameraIntrinsic(320, 240, 300.0, 310.0, 160.5, 119.5)
    path = tmp_path / "intrinsic.json"
    o3d.io.write_pinhole_camera_intrinsic(str(path), camera)
    intr = read_intrinsics(path)
    assert np.array_equal(intr.K, camera.intrinsic_matrix)
    assert (intr.width, intr.height) == (320, 240)


def test_json_pinhole_parameters_and_no_size(tmp_path):
    path = tmp_path / "camera.json"
    matrix = K_FR1.flatten(order="F").tolist()
    path.write_text(json.dumps({"extrinsic": [1] * 16, "intrinsic": {"intrinsic_matrix": matrix}}))
    intr = read_intrinsics(path)
    assert np.array_equal(intr.K, K_FR1) and intr.width is None and intr.height is None


def test_text_matrix_3dmatch_and_scannet(shared_data, tmp_path):
    intr = read_intrinsics(shared_data / "rgbd" / "realsense_tabletop" / "camera-intrinsics.txt")
    assert intr.K[0, 0] == pytest.approx(615.1951904296875)
    assert intr.K[1, 2] == pytest.approx(247.51919555664062)
    assert intr.width is None and intr.height is None
    scannet = tmp_path / "intrinsic_depth.txt"
    scannet.write_text("577.59 0 318.90 0\n0 578.73 242.68 0\n0 0 1 0\n0 0 0 1\n")
    assert read_intrinsics(scannet).K[0, 2] == pytest.approx(318.90)
    tabs = tmp_path / "tabs.txt"
    tabs.write_text("500\t0\t320 \n0\t500\t240\n0\t0\t1\n\n")
    assert read_intrinsics(tabs).K[1, 1] == 500


BAD_INTRINSICS = {
    "t.json": ('{"width": 640, "intrinsic_matrix": [1, 2', "not valid JSON (line 1"),
    "nokey.json": ('{"width": 640}', "JSON lacks 'intrinsic_matrix'"),
    "eight.json": ('{"intrinsic_matrix": [1, 0, 0, 0, 1, 0, 0, 0]}', "has 8 numbers, expected 9"),
    "nested.json": ('{"intrinsic_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}', "flat list of 9"),
    "row_major.json": (
        json.dumps({"intrinsic_matrix": K_FR1.flatten().tolist()}),
        "intrinsic matrix rows are [517.3, 0, 0], [0, 516.5, 0], [318.6, 255.3, 1]",
    ),
    "width.json": (
        json.dumps({"width": -3, "intrinsic_matrix": K_FR1.flatten(order="F").tolist()}),
        "'width' must be a positive integer, got -3",
    ),
    "negative.txt": ("-500 0 320\n0 500 240\n0 0 1\n", "focal lengths must be positive"),
    "transposed.txt": ("500 0 0\n0 500 0\n320 240 1\n", "expected [fx, s, cx], [0, fy, cy]"),
    "2x3.txt": ("500 0 320\n0 500 240\n", "expected a 3x3 matrix, found 2 rows of 3 numbers"),
    "words.txt": ("fx = 500\n", "not a numeric matrix (line 1"),
    "nan.txt": ("nan 0 320\n0 500 240\n0 0 1\n", "intrinsic matrix has NaN or Inf entries"),
}


@pytest.mark.parametrize("name", sorted(BAD_INTRINSICS))
def test_bad_intrinsics(tmp_path, name):
    text, problem = BAD_INTRINSICS[name]
    path = tmp_path / name
    path.write_text(text)
    assert problem in _error(read_intrinsics, path, path)


def test_intrinsics_missing_and_binary(tmp_path):
    assert _error(read_intrinsics, tmp_path / "no.txt", tmp_path / "no.txt") == "no such file"
    (tmp_path / "b.txt").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    assert _error(read_intrinsics, tmp_path / "b.txt", tmp_path / "b.txt") == "not a text file"


# ---------------------------------------------------------------- back-projection


def test_depth_to_points_hand_example():
    K = np.array([[100.0, 0, 2.0], [0, 50.0, 1.0], [0, 0, 1]])
    depth = np.zeros((2, 4))
    depth[0, 3] = 2.0  # u=3, v=0
    depth[1, 0] = 1.0  # u=0, v=1
    depth[1, 1] = np.nan
    depth[0, 0] = -1.0
    points = depth_to_points(depth, K)
    # centres: (3.5 - 2) * 2 / 100 = 0.03, (0.5 - 1) * 2 / 50 = -0.02; row-major order
    assert np.allclose(points, [[0.03, -0.02, 2.0], [-0.015, 0.01, 1.0]])
    corners = depth_to_points(depth, K, pixel_offset=0.0)
    assert np.allclose(corners, [[0.02, -0.04, 2.0], [-0.02, 0.0, 1.0]])
    assert depth_to_points(np.zeros((3, 3)), K).shape == (0, 3)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    h=st.integers(1, 12),
    w=st.integers(1, 12),
    skew=st.floats(-5, 5),
)
def test_projection_returns_pixel_centres(seed, h, w, skew):
    rng = np.random.default_rng(seed)
    K = np.array(
        [
            [rng.uniform(50, 800), skew, rng.uniform(0, w)],
            [0, rng.uniform(50, 800), rng.uniform(0, h)],
            [0, 0, 1],
        ]
    )
    depth = rng.uniform(0.1, 10.0, size=(h, w))
    depth[rng.random((h, w)) < 0.3] = 0.0
    points = depth_to_points(depth, K)
    v, u = np.nonzero(depth > 0)
    assert points.shape == (len(u), 3)
    assert np.allclose(points[:, 2], depth[v, u])
    projected = points @ K.T
    assert np.allclose(projected[:, :2] / projected[:, 2:], np.stack([u, v], 1) + 0.5)


def test_depth_to_points_shapes():
    with pytest.raises(ShapeError):
        depth_to_points(np.zeros((2, 2, 1)), np.eye(3))
    with pytest.raises(ShapeError):
        depth_to_points(np.zeros((2, 2)), np.eye(4))
    with pytest.raises(ValueError, match="invertible"):
        depth_to_points(np.zeros((2, 2)), np.diag([0.0, 1.0, 1.0]))


def test_matches_open3d_with_zero_offset(shared_data):
    try:
        o3d = require_open3d()
    except DependencyError as exc:
        pytest.skip(str(exc))
    folder = shared_data / "rgbd" / "tum_fr1_xyz"
    depth_path = _first_depth(folder / "depth", "*.png")
    depth = read_depth_image(depth_path, 5000.0)
    ours = depth_to_points(depth, K_FR1, pixel_offset=0.0)
    camera = o3d.camera.PinholeCameraIntrinsic(640, 480, 517.3, 516.5, 318.6, 255.3)
    image = o3d.io.read_image(str(depth_path))
    theirs = o3d.geometry.PointCloud.create_from_depth_image(
        image, camera, depth_scale=5000.0, depth_trunc=1000.0
    )
    assert np.allclose(ours, np.asarray(theirs.points), atol=1e-6)


# ---------------------------------------------------------------- depth images


def test_read_depth_image_16bit(tmp_path):
    raw = np.array([[0, 1000, 65535], [1500, 65534, 1]], dtype=np.uint16)
    path = tmp_path / "d.png"
    _save_depth16(path, raw)
    depth = read_depth_image(path, 1000.0)
    assert depth.dtype == np.float32 and depth.shape == (2, 3)
    assert np.array_equal(depth, np.float32([[0, 1.0, 0], [1.5, 65.534, 0.001]]))
    assert read_depth_image(path, 5000.0)[1, 0] == np.float32(0.3)


def test_read_depth_image_float_tiff(tmp_path):
    depth = np.array([[0.5, np.nan], [0.0, 2.25]], dtype=np.float32)
    path = tmp_path / "d.tiff"
    Image.fromarray(depth, mode="F").save(path)
    back = read_depth_image(path, 1.0)
    assert np.array_equal(back, depth, equal_nan=True)


def test_depth_image_errors(tmp_path):
    rgb = tmp_path / "rgb.png"
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(rgb)
    assert _error(read_depth_image, rgb, rgb, 1000).startswith(
        "not a depth image (pixel format 'RGB'"
    )
    gray8 = tmp_path / "gray8.png"
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(gray8)
    assert "pixel format 'L'" in _error(read_depth_image, gray8, gray8, 1000)
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image at all")
    assert _error(read_depth_image, junk, junk, 1000) == (
        "not an image file (pillow cannot identify it)"
    )
    good = tmp_path / "good.png"
    _save_depth16(good, np.random.default_rng(0).integers(0, 5000, (240, 320)))
    cut = tmp_path / "cut.png"
    cut.write_bytes(good.read_bytes()[:2000])
    assert _error(read_depth_image, cut, cut, 1000).startswith("truncated or corrupt image")
    missing = tmp_path / "missing.png"
    assert _error(read_depth_image, missing, missing, 1000) == "no such file"
    with pytest.raises(ValueError, match="depth_scale"):
        read_depth_image(good, 0.0)


# ---------------------------------------------------------------- depth clouds


def test_tum_frame(shared_data):
    folder = shared_data / "rgbd" / "tum_fr1_xyz"
    depth_path = _first_depth(folder / "depth", "*.png")
    cloud = read_depth_cloud(depth_path, folder / "intrinsics.json", depth_scale=5000.0)
    assert isinstance(cloud, LoadedCloud) and cloud.path == depth_path
    raw = np.asarray(Image.open(depth_path))
    assert cloud.points.shape == (np.count_nonzero(raw), 3)
    assert cloud.num_nonfinite_dropped == 0
    z = cloud.points[:, 2]
    assert 0.3 < z.min() and z.max() < 6.0  # an office desk, in metres
    near = read_depth_cloud(depth_path, folder / "intrinsics.json", 5000.0, depth_trunc=1.0)
    assert near.points[:, 2].max() <= 1.0 and 0 < len(near.points) < len(cloud.points)


def test_realsense_frame_in_millimetres(shared_data):
    folder = shared_data / "rgbd" / "realsense_tabletop"
    depth_path = _first_depth(folder / "seq-01", "frame-*.depth.png")
    cloud = read_depth_cloud(depth_path, folder / "camera-intrinsics.txt")  # mm by default
    z = cloud.points[:, 2]
    assert 0.05 < z.min() and z.max() < 3.0  # a box on a table
    assert len(cloud.points) > 10_000


def test_depth_cloud_errors(tmp_path, shared_data):
    intrinsics = shared_data / "rgbd" / "tum_fr1_xyz" / "intrinsics.json"
    small = tmp_path / "small.png"
    _save_depth16(small, np.full((240, 320), 5000))
    problem = _error(read_depth_cloud, intrinsics, small, intrinsics, 5000.0)
    assert problem == "intrinsics are for 640x480 images but small.png is 320x240"
    zeros = tmp_path / "zeros.png"
    _save_depth16(zeros, np.zeros((480, 640)))
    assert _error(read_depth_cloud, zeros, zeros, intrinsics, 5000.0) == (
        "no valid depth pixels (all 0 or invalid)"
    )
    far = tmp_path / "far.png"
    _save_depth16(far, np.full((480, 640), 50000))  # 10 m
    assert "within depth_trunc 3 m" in _error(
        read_depth_cloud, far, far, intrinsics, 5000.0, depth_trunc=3.0
    )
    missing = tmp_path / "K.txt"
    assert _error(read_depth_cloud, missing, far, missing) == "no such file"
    with pytest.raises(ValueError, match="depth_trunc"):
        read_depth_cloud(far, intrinsics, 5000.0, depth_trunc=-1.0)


def test_depth_works_without_open3d(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)
    path = tmp_path / "d.png"
    _save_depth16(path, np.full((4, 5), 1000))
    K = tmp_path / "K.txt"
    K.write_text("10 0 2.5\n0 10 2\n0 0 1\n")
    cloud = read_depth_cloud(path, K)
    assert cloud.points.shape == (20, 3) and np.allclose(cloud.points[:, 2], 1.0)


@pytest.mark.parametrize(
    ("text", "phrase"),
    [
        ("1e-7 0 16\n0 1e-7 12\n0 0 1\n", "not plausible"),
        ("5e9 0 16\n0 5e9 12\n0 0 1\n", "not plausible"),
        ("500 0 1e12\n0 500 12\n0 0 1\n", "principal point or skew"),
    ],
)
def test_implausible_intrinsics_are_refused(tmp_path, text, phrase):
    path = tmp_path / "K.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=phrase) as info:
        read_intrinsics(path)
    assert info.value.path == str(path)


@pytest.mark.parametrize("width", ["1e400", "1e9", "NaN", "-Infinity"])
def test_absurd_image_sizes_are_refused(tmp_path, width):
    path = tmp_path / "K.json"
    matrix = K_FR1.flatten("F").tolist()
    path.write_text(f'{{"width": {width}, "intrinsic_matrix": {matrix}}}')
    with pytest.raises(InputError, match="'width'"):
        read_intrinsics(path)


def test_depth_image_larger_than_any_depth_camera_is_refused(tmp_path, monkeypatch):
    import byoc_cli.io.depth as depth_module

    path = tmp_path / "d.png"
    Image.fromarray(np.ones((40, 50), dtype=np.uint16)).save(path)
    monkeypatch.setattr(depth_module, "MAX_DEPTH_PIXELS", 1999)
    with pytest.raises(InputError, match="larger than a depth image can be"):
        read_depth_image(path, 1000.0)
