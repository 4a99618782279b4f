"""The scale and feature stages of one cloud (pipeline/featurizer.py)."""

from __future__ import annotations

import numpy as np
import pytest

from byoc_cli.pipeline.registrar import Registrar
from tests.pipeline._clouds import cube


def test_features_from_a_share_of_the_points_index_the_whole_cloud():
    pts = cube(2)
    registrar = Registrar("fpfh")
    full = registrar.extract_points(pts, None, "cloud", 0.05)
    part = registrar.extract_points(pts, None, "cloud", 0.05, keep=0.25)
    again = registrar.extract_points(pts, None, "cloud", 0.05, keep=0.25)
    assert part.cloud is pts  # the refinement runs on every point
    np.testing.assert_array_equal(part.points, pts[part.point_index])
    assert part.point_index.max() >= len(pts) * 0.5  # indices of the whole cloud, not the share
    assert len(part.points) < len(full.points)
    np.testing.assert_array_equal(part.point_index, again.point_index)  # seeded


def test_a_far_cloud_is_featured_about_its_median_point_and_strays_left_out():
    made = Registrar("fpfh", voxel_size=0.05)
    near = cube(2)
    offset = np.array([4.5e5, 5.2e6, 10.0])
    far = np.vstack([near + offset, offset + 1e6])  # one stray point a million metres off
    f_near = made.extract_points(near, None, "near")
    f_far = made.extract_points(far, None, "far")
    assert f_near.origin is None and f_far.origin is not None
    assert np.abs(f_far.origin - offset).max() < 1.0
    assert len(far) - 1 not in set(f_far.point_index.tolist())  # the stray is left out
    # voxels of a grid about the median point: as many as about the origin, give or take
    assert abs(len(f_far.point_index) - len(f_near.point_index)) < 0.02 * len(f_near.points)
    np.testing.assert_array_equal(f_far.points, far[f_far.point_index])  # input coordinates


def test_a_clouds_scale_and_frame_are_computed_once_per_array(monkeypatch):
    import byoc_cli.pipeline.scale as scale

    made, calls = Registrar("fpfh"), []
    real = scale.measure
    monkeypatch.setattr(
        scale,
        "measure",
        lambda p, label="c", lines=True, **kw: calls.append(label) or real(p, lines=lines, **kw),
    )
    lines = []
    real_lines = scale.scan_line_voxel
    monkeypatch.setattr(scale, "scan_line_voxel", lambda *a: lines.append(1) or real_lines(*a))
    a = cube(3)
    quick = made.cloud_scale(a, "a", lines=False)  # the local path's: no scan lines
    assert quick.line_voxel is None and not lines
    first = made.cloud_scale(a, "a")
    again = made.cloud_scale(a, "renamed")
    assert calls == ["a"] and again.label == "renamed" and again.spacing == first.spacing
    assert lines == [1] and first.line_voxel == again.line_voxel == 0.0
    assert made.frame(a) is made.frame(a)
    assert made.spread(a) is made.spread(a)  # one median and radius for the scale and frame
    assert made.frame(a).radius == first.radius == made.spread(a).radius
    made.cloud_scale(a.copy(), "copy")  # another array: measured
    assert calls == ["a", "copy"]


def test_keep_subset_is_seeded_sorted_and_at_least_one():
    from byoc_cli.pipeline.featurizer import keep_subset

    assert keep_subset(100, 1.0) is None and keep_subset(0, 0.5) is None
    a, b = keep_subset(1000, 0.3), keep_subset(1000, 0.3)
    np.testing.assert_array_equal(a, b)
    assert len(a) == 300 and np.all(np.diff(a) > 0)
    assert len(keep_subset(10, 0.001)) == 1


def test_weights_at_another_voxel_warn():
    from byoc_cli.pipeline.default_weights import default_weights_path

    if default_weights_path() is None:
        pytest.skip("this install ships no weights")
    with pytest.warns(UserWarning, match="differs from the 0.025 m"):
        Registrar(voxel_size=0.05)
