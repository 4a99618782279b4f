"""Quality files: residuals against a naive reference, a PNG whose pixels show both clouds in
their two colours and the residual colours below, a residual PLY, far coordinates, samples."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from plyfile import PlyData

from byoc_cli.errors import ShapeError
from byoc_cli.evaluation.qc import (
    SOURCE_RGB,
    TARGET_RGB,
    QcSettings,
    qc_paths,
    residuals,
    write_qc,
)

#: a UTM easting, northing and height
UTM = np.array([512345.678, 4123456.789, 123.4])


def _room(n: int, seed: int) -> np.ndarray:
    """Points on the floor and two walls of a 4 x 3 x 2.5 m room corner."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 1, (n, 3)) * [4.0, 3.0, 2.5]
    face = rng.integers(0, 3, n)
    points[face == 0, 2] = 0.0
    points[face == 1, 0] = 0.0
    points[face == 2, 1] = 0.0
    return points


def _turn(degrees: float, shift) -> np.ndarray:
    a = np.radians(degrees)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = shift
    return T


def _pair(seed: int = 0):
    """A target, a source that is the target seen from elsewhere, and the right T_tgt_src."""
    tgt = _room(6000, seed)
    T = _turn(20.0, [0.5, -0.3, 0.1])
    src = (tgt[:5000] - T[:3, 3]) @ T[:3, :3]  # inverse of T: T brings it back onto tgt
    return src, tgt, T


def _count(pixels: np.ndarray, rgb) -> int:
    return int(np.all(pixels == np.asarray(rgb), axis=-1).sum())


def _png(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB")).astype(int)


def _below(path) -> np.ndarray:
    """The lower half of a figure: the residual views."""
    pixels = _png(path)
    return pixels[pixels.shape[0] // 2 :]


def test_residuals_match_a_naive_nearest_neighbour():
    rng = np.random.default_rng(1)
    src, tgt = rng.normal(size=(200, 3)), rng.normal(size=(300, 3))
    naive = np.sqrt(((src[:, None, :] - tgt[None, :, :]) ** 2).sum(-1)).min(axis=1)
    np.testing.assert_allclose(residuals(src, tgt), naive, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(residuals(src + UTM, tgt + UTM), naive, atol=1e-8)  # far out
    assert residuals(np.zeros((0, 3)), tgt).shape == (0,)
    # hand-worked: (1, 0, 0) is 1 from (0, 0, 0); (3, 4, 0) is 5 from it
    np.testing.assert_allclose(residuals([[1.0, 0, 0], [3.0, 4.0, 0]], [[0.0, 0, 0]]), [1, 5])


def test_the_png_shows_both_clouds_in_their_colours_and_residuals_below(tmp_path):
    src, tgt, T = _pair()
    done = write_qc(tmp_path, "pair", src, tgt, T, QcSettings(clip=0.05, unit="m", title="t"))
    assert (done.png, done.ply) == qc_paths(tmp_path, "pair")
    pixels = _png(done.png)
    height = pixels.shape[0]
    overlay, below = pixels[: height // 2], pixels[height // 2 :]
    assert _count(overlay, TARGET_RGB) > 2000 and _count(overlay, SOURCE_RGB) > 2000
    assert _count(below, TARGET_RGB) == _count(below, SOURCE_RGB) == 0
    not_white = np.any(pixels != 255, axis=-1).mean()
    assert 0.05 < not_white < 0.9  # drawn, not blank and not a solid fill
    # right T: every moved source point lies on the target (the residual row's low colour)
    assert done.median_residual < 1e-9 and done.within_clip == 1.0
    viridis_low = (68, 1, 84)
    assert _count(below, viridis_low) > 2000


def test_a_wrong_T_shows_as_large_residuals(tmp_path):
    src, tgt, T = _pair()
    right = write_qc(tmp_path, "right", src, tgt, T, QcSettings(clip=0.05))
    wrong = write_qc(tmp_path, "wrong", src, tgt, _turn(0.0, [1.0, 0, 0]), QcSettings(clip=0.05))
    assert wrong.median_residual > 0.05 > right.median_residual
    assert wrong.within_clip < 0.5
    viridis_high = (253, 231, 37)
    wrong_below, right_below = (_below(p) for p in (wrong.png, right.png))
    assert _count(wrong_below, viridis_high) > 1000 > _count(right_below, viridis_high)


def test_the_residual_ply_is_the_moved_source_coloured_and_with_its_residual(tmp_path):
    src, tgt, T = _pair()
    T_off = _turn(0.0, [0.02, 0.0, 0.0]) @ T  # 2 cm off: residuals up to 2 cm
    done = write_qc(tmp_path, "p", src, tgt, T_off, QcSettings(clip=0.04))
    vertex = PlyData.read(str(done.ply))["vertex"]
    got = np.column_stack([vertex[k] for k in "xyz"]).astype(np.float64)
    moved = src @ T_off[:3, :3].T + T_off[:3, 3]
    assert got.shape == moved.shape and np.abs(got - moved).max() < 1e-5
    np.testing.assert_allclose(vertex["residual"], residuals(moved, tgt), atol=1e-6)
    assert vertex["residual"].max() <= 0.02 + 1e-6
    colors = np.column_stack([vertex[k] for k in ("red", "green", "blue")])
    assert colors.dtype == np.uint8 and len(np.unique(colors, axis=0)) > 10


def test_far_coordinates_give_the_same_files_about_a_stated_origin(tmp_path):
    src, tgt, T = _pair()
    shift = np.eye(4)
    shift[:3, 3] = UTM
    T_far = shift @ T @ np.linalg.inv(shift)
    near = write_qc(tmp_path, "near", src, tgt, T, QcSettings(clip=0.05))
    far = write_qc(tmp_path, "far", src + UTM, tgt + UTM, T_far, QcSettings(clip=0.05))
    assert far.median_residual < 1e-6 and far.within_clip == 1.0 == near.within_clip
    vertex = PlyData.read(str(far.ply))["vertex"]
    assert vertex["x"].dtype == np.float64  # UTM kept in the PLY
    pixels = _png(far.png)
    overlay = pixels[: pixels.shape[0] // 2]
    assert _count(overlay, TARGET_RGB) > 2000 and _count(overlay, SOURCE_RGB) > 2000


def test_large_clouds_are_sampled(tmp_path):
    src, tgt, T = _pair()
    settings = QcSettings(clip=0.05, max_draw_points=500, max_ply_points=1000, seed=3)
    done = write_qc(tmp_path, "s", src, tgt, T, settings)
    assert PlyData.read(str(done.ply))["vertex"].count == 1000
    assert (done.num_points_src, done.num_points_tgt) == (5000, 6000)
    again = write_qc(tmp_path, "t", src, tgt, T, settings)
    assert done.ply.read_bytes() == again.ply.read_bytes()  # seeded


@pytest.mark.parametrize(
    ("src", "T", "clip"),
    [
        (np.zeros((0, 3)), np.eye(4), 0.1),
        (np.full((3, 3), np.nan), np.eye(4), 0.1),
        (np.zeros((3, 3)), np.eye(3), 0.1),
        (np.zeros((3, 3)), np.eye(4), 0.0),
        (np.zeros((3, 3)), np.eye(4), float("inf")),
    ],
)
def test_bad_arguments_are_shape_errors_and_write_nothing(tmp_path, src, T, clip):
    with pytest.raises(ShapeError):
        write_qc(tmp_path, "x", src, np.zeros((3, 3)), T, QcSettings(clip=clip))
    assert not list(tmp_path.iterdir())
