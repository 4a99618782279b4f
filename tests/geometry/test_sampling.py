"""Point spacing and cloud radius without units: against brute force, invariances."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.sampling import (
    SPACING_NEIGHBOURS,
    cloud_radius,
    local_frame,
    nearest_spacing,
)


def _brute_spacing(points: np.ndarray) -> float:
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    d[d <= 0] = np.inf
    return float(np.median(d.min(axis=1)))


def _surface(n: int, seed: int, size: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, size, (n, 2))
    return np.column_stack([xy, 0.1 * size * np.sin(3 * xy[:, 0] / size)])


def test_spacing_equals_brute_force_when_every_point_is_a_query():
    pts = _surface(1500, 0)
    got = nearest_spacing(torch.from_numpy(pts), samples=len(pts))
    assert got == pytest.approx(_brute_spacing(pts), rel=1e-9)


def test_many_copies_of_a_point_are_not_the_spacing():
    # a scanner's repeated returns at its sensor: more copies than the neighbours asked
    pts = _surface(3000, 4)
    copies = np.concatenate([pts, np.repeat(pts[:5], 3 * SPACING_NEIGHBOURS, axis=0)])
    every = nearest_spacing(torch.from_numpy(copies), samples=len(copies))
    d = np.linalg.norm(copies[:, None] - pts[None], axis=2)
    d[d <= 0] = np.inf
    assert every == pytest.approx(float(np.median(d.min(axis=1))), rel=1e-9)


def test_distinct_points_repeated_many_times():
    ten = _surface(10, 5)
    repeated = torch.from_numpy(np.repeat(ten, 2000, axis=0))
    assert nearest_spacing(repeated) == pytest.approx(_brute_spacing(ten), rel=0.5)
    assert nearest_spacing(repeated) > 0


def test_spacing_of_a_grid_is_its_step():
    g = np.arange(40) * 0.01
    pts = np.stack(np.meshgrid(g, g, [0.0]), -1).reshape(-1, 3)
    assert nearest_spacing(torch.from_numpy(pts)) == pytest.approx(0.01, rel=1e-6)


@settings(max_examples=20, deadline=None)
@given(st.floats(1e-3, 1e3), st.integers(0, 50))
def test_spacing_and_radius_scale_with_the_cloud(factor, seed):
    pts = torch.from_numpy(_surface(800, seed))
    s0, r0 = nearest_spacing(pts), cloud_radius(pts)
    assert nearest_spacing(pts * factor) == pytest.approx(s0 * factor, rel=1e-6)
    assert cloud_radius(pts * factor) == pytest.approx(r0 * factor, rel=1e-9)


def test_duplicates_are_not_the_spacing():
    pts = _surface(500, 1)
    doubled = torch.from_numpy(np.concatenate([pts, pts]))
    assert nearest_spacing(doubled, samples=1000) == pytest.approx(_brute_spacing(pts), rel=1e-9)


def test_thinning_widens_the_spacing():
    pts = _surface(20000, 2)
    full = nearest_spacing(torch.from_numpy(pts))
    quarter = nearest_spacing(torch.from_numpy(pts[::4]))
    assert 1.7 < quarter / full < 2.3  # a surface: spacing grows with sqrt(1/density)


def test_radius_ignores_a_few_far_points():
    pts = _surface(1000, 3)
    far = np.concatenate([pts, np.full((10, 3), 1e6)])
    assert cloud_radius(torch.from_numpy(far)) == pytest.approx(
        cloud_radius(torch.from_numpy(pts)), rel=0.05
    )


def test_degenerate_sizes():
    assert nearest_spacing(torch.zeros(0, 3)) == 0.0
    assert nearest_spacing(torch.zeros(5, 3)) == 0.0  # one distinct point
    assert cloud_radius(torch.zeros(1, 3)) == 0.0
    with pytest.raises(ShapeError):
        nearest_spacing(torch.zeros(4, 2))


def test_a_cloud_near_the_origin_is_registered_where_it_is():
    pts = _surface(2000, 6, size=3.0) + 5.0
    frame = local_frame(pts)
    assert not frame.moved and frame.inside is None and frame.strays == 0
    assert frame.local(pts) is pts


@pytest.mark.parametrize("offset", [1e4, 1e6, 1e7, 1e9])
def test_a_far_cloud_is_registered_about_its_median_point_without_rounding(offset):
    pts = _surface(2000, 7, size=3.0)
    far = pts + np.array([offset, -2 * offset, 0.5 * offset])
    frame = local_frame(far)
    assert frame.moved
    np.testing.assert_array_equal(frame.origin, np.median(far, axis=0))
    local = frame.local(far)
    # the median is a point of the cloud's box: subtracting it is exact (Sterbenz)
    np.testing.assert_array_equal(local + frame.origin, far)
    assert np.abs(local).max() < 10


def test_far_strays_are_left_out_and_the_rest_kept_in_order():
    pts = _surface(2000, 8)
    strays = np.array([[1e6, 0, 0], [0, -1e30, 0], [np.finfo(np.float64).max] * 3])
    mixed = np.concatenate([pts[:1000], strays, pts[1000:]])
    frame = local_frame(mixed)
    assert frame.strays == 3 and not frame.moved
    np.testing.assert_array_equal(frame.local(mixed), pts)


@settings(max_examples=25, deadline=None)
@given(st.floats(1e-6, 1e6), st.integers(0, 30))
def test_the_strays_do_not_depend_on_the_unit(factor, seed):
    pts = _surface(500, seed)
    with_far = np.concatenate([pts, [[3e3, 0, 0]]]) * factor
    frame = local_frame(with_far)
    assert frame.strays == 1
    assert frame.radius == pytest.approx(cloud_radius(torch.from_numpy(with_far)), rel=1e-9)


def test_no_stray_without_a_radius():
    pts = np.concatenate([np.zeros((10, 3)), [[1.0, 0, 0]]])  # most points in one place
    frame = local_frame(pts)
    assert frame.radius == 0 and frame.inside is None and not frame.moved
