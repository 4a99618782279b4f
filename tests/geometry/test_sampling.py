"""Point spacing, cloud radius and scan lines without units: against brute force, invariances."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.sampling import (
    LINE_MIN_POINTS,
    SPACING_NEIGHBOURS,
    STRAY_RADII,
    _first_per_voxel,
    cloud_radius,
    even_radius,
    first_of_keys,
    linear_share,
    local_frame,
    nearest_distances,
    nearest_spacing,
    rough_share,
    spacing_spread,
    spread,
    surround_share,
)
from byoc_cli.geometry.voxel import voxelize
from tests._rings import camera_scan, ring_scan, room_scan


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


def test_the_even_radius_of_a_laser_scanned_room_is_the_room_not_where_its_points_crowd():
    room = room_scan()  # 7 x 5 x 2.8 m, scanned from inside: dense near the scanner
    assert even_radius(room) > 1.3 * cloud_radius(room)
    assert 2.5 < even_radius(room) < 3.2  # the box's own median distance from its centre
    surface = _surface(20_000, 4)  # sampled evenly: the same both ways
    assert even_radius(surface) == pytest.approx(cloud_radius(surface), rel=0.05)


@pytest.mark.parametrize("factor", [1e-3, 1.0, 1e3])
def test_the_even_radius_does_not_depend_on_the_unit_or_on_strays_far_away(factor):
    room = room_scan(2.0)
    strays = np.concatenate([room, np.full((3, 3), 1e6)])
    assert even_radius(room * factor) == pytest.approx(even_radius(room) * factor, rel=1e-9)
    assert even_radius(strays) == pytest.approx(even_radius(room), rel=0.02)
    assert even_radius(torch.from_numpy(room)) == even_radius(room)


def test_the_spacing_spread_tells_an_even_scan_from_one_whose_step_grows_with_range():
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(60.0), np.arange(60.0), [0.0]), -1).reshape(-1, 3)
    even = grid * 0.5 + rng.normal(0.0, 0.02, grid.shape)  # a surface sampled evenly
    assert spacing_spread(nearest_distances(torch.from_numpy(even))) < 2.0
    rings = ring_scan()  # a spinning LiDAR: the step grows with the range
    assert spacing_spread(nearest_distances(torch.from_numpy(rings))) > 3.0
    found = nearest_distances(torch.from_numpy(even))
    assert np.median(found) == nearest_spacing(torch.from_numpy(even))
    assert len(nearest_distances(torch.zeros(5, 3))) == 0  # one distinct point
    assert np.isnan(spacing_spread(np.zeros(0)))


def test_a_panorama_surrounds_its_origin_and_a_camera_frame_does_not():
    room = room_scan()
    assert surround_share(room) > 0.9 and surround_share(camera_scan()) < 0.1
    assert surround_share(room + np.array([20.0, 0.0, 0.0])) < 0.1  # seen from elsewhere
    assert surround_share(np.zeros((0, 3))) == 0.0


def test_degenerate_sizes():
    assert nearest_spacing(torch.zeros(0, 3)) == 0.0
    assert nearest_spacing(torch.zeros(5, 3)) == 0.0  # one distinct point
    assert cloud_radius(torch.zeros(1, 3)) == 0.0
    assert even_radius(torch.zeros(1, 3)) == 0.0 and even_radius(np.zeros((5, 3))) == 0.0
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


def test_spread_is_the_median_point_and_the_median_distance_from_it():
    pts = _surface(1001, 9) + np.array([2.0, -1.0, 0.5])
    centre, radius = spread(pts)
    np.testing.assert_array_equal(centre, [np.median(pts[:, k]) for k in range(3)])
    assert radius == np.median(np.sqrt(((pts - centre) ** 2).sum(axis=1)))
    t_centre, t_radius = spread(torch.from_numpy(pts))
    np.testing.assert_array_equal(t_centre, centre)
    assert t_radius == radius == cloud_radius(torch.from_numpy(pts))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 1000), st.floats(10.0, 1e5), st.integers(0, 3))
def test_the_box_shortcut_finds_the_strays_a_point_by_point_test_finds(seed, far, count):
    """No stray when the box's farthest corner is within reach; else each point's test."""
    rng = np.random.default_rng(seed)
    pts = np.concatenate([_surface(300, seed % 50), rng.normal(size=(count, 3)) * far])
    frame = local_frame(pts)
    centre, radius = spread(pts)
    inside = np.linalg.norm(pts - centre, axis=1) <= STRAY_RADII * radius
    if frame.inside is None:
        assert inside.all()
    else:
        np.testing.assert_array_equal(frame.inside, inside)
    assert frame.radius == radius
    given_spread = local_frame(pts, spread(pts))
    np.testing.assert_array_equal(given_spread.origin, frame.origin)
    assert given_spread.strays == frame.strays and given_spread.radius == frame.radius


def test_no_stray_without_a_radius():
    pts = np.concatenate([np.zeros((10, 3)), [[1.0, 0, 0]]])  # most points in one place
    frame = local_frame(pts)
    assert frame.radius == 0 and frame.inside is None and not frame.moved


def _parallel_lines(gap: float, step: float = 0.01, size: float = 4.0) -> np.ndarray:
    """Points every ``step`` along lines ``gap`` apart on a plane: scan lines at their
    sampling step."""
    x, y = np.meshgrid(np.arange(0.0, size, step), np.arange(0.0, size, gap))
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def test_the_kept_points_are_those_of_voxelize():
    for pts in (ring_scan(), _surface(3000, 9, size=2.0) - 1.0):
        points = torch.from_numpy(pts)
        for voxel in (0.02, 0.1, 0.7):
            expected = voxelize(points, voxel).point_index.numpy()
            np.testing.assert_array_equal(_first_per_voxel(pts, voxel), expected)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(-(2**62), 2**62), max_size=300), st.integers(1, 40))
def test_first_of_keys_is_the_first_occurrence_of_each_key(values, distinct):
    keys = np.array([v % distinct for v in values] + values[:5], dtype=np.int64)
    expected = np.sort(np.unique(keys, return_index=True)[1])
    got = first_of_keys(keys)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, expected)


def test_lines_are_lines_until_the_voxel_reaches_across_them():
    lines = torch.from_numpy(_parallel_lines(0.5))
    # the neighbourhood reaches 2.5 voxels: one line below 0.2, two lines from there on
    assert linear_share(lines, 0.05) == 1.0 and linear_share(lines, 0.19) == 1.0
    assert linear_share(lines, 0.21) == 0.0 and linear_share(lines, 0.5) == 0.0


def test_a_ring_scan_shows_its_rings_and_a_camera_grid_of_the_same_scene_does_not():
    rings, camera = torch.from_numpy(ring_scan()), torch.from_numpy(camera_scan())
    at_step = [linear_share(c, 1.8 * nearest_spacing(c)) for c in (rings, camera)]
    assert at_step[0] > 0.9 and at_step[1] < 0.1
    # the rings wash out as the voxel grows past their gaps (the far ones never do)
    assert linear_share(rings, 0.1) > linear_share(rings, 0.4) > linear_share(rings, 1.2)


def test_an_evenly_sampled_surface_has_no_lines_at_any_voxel():
    surface = torch.from_numpy(_surface(20000, 10, size=2.0))
    assert max(linear_share(surface, v) for v in (0.02, 0.05, 0.1, 0.2)) < 0.02


@settings(max_examples=10, deadline=None)
@given(st.floats(1e-3, 1e3))
def test_the_share_of_lines_does_not_depend_on_the_unit(factor):
    rings = ring_scan(rings=8, steps=600)
    got = linear_share(torch.from_numpy(rings * factor), 0.3 * factor)
    assert got == pytest.approx(linear_share(torch.from_numpy(rings), 0.3), abs=0.02)


def test_linear_share_of_degenerate_clouds():
    assert linear_share(torch.zeros(0, 3), 0.1) == 0.0
    few = torch.from_numpy(_surface(LINE_MIN_POINTS - 1, 11))
    assert linear_share(few, 0.01) == 0.0
    spread = torch.tensor([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [10, 10, 10.0]])
    assert linear_share(spread, 1.0) == 0.0  # no point has neighbours: none counted
    with pytest.raises(ShapeError):
        linear_share(torch.zeros(4, 2), 0.1)
    with pytest.raises(ShapeError):
        linear_share(torch.zeros(4, 3), 0.0)


def _sphere(n: int, seed: int, radius: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 3))
    return radius * u / np.linalg.norm(u, axis=1, keepdims=True)


def _box(n: int, seed: int, size: float = 1.0) -> np.ndarray:
    """Points on the faces of a cube: planes meeting at edges and corners."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(0, size, (n, 3))
    axis, side = rng.integers(0, 3, n), rng.integers(0, 2, n)
    p[np.arange(n), axis] = side * size
    return p


def test_a_smooth_sphere_is_not_rough_and_a_box_is_at_its_edges():
    # 40 voxels across the radius, as the auto voxel makes it; the box: 40 voxels a side
    sphere = torch.from_numpy(_sphere(60000, 0))
    assert rough_share(sphere, 1 / 40) < 0.02
    box = torch.from_numpy(_box(60000, 1))
    assert rough_share(box, 1 / 40) > 0.05  # the neighbourhoods at the 12 edges, 8 corners


def test_noise_or_clutter_makes_a_surface_rough():
    rng = np.random.default_rng(2)
    sphere = _sphere(60000, 3)
    noisy = sphere + rng.normal(0, 0.5 / 40, sphere.shape)  # half a voxel
    assert rough_share(torch.from_numpy(noisy), 1 / 40) > 0.5
    clutter = rng.uniform(-1, 1, (60000, 3))
    assert rough_share(torch.from_numpy(clutter), 0.1) > 0.9


@pytest.mark.parametrize("factor", [1e-3, 1e3])
def test_the_rough_share_does_not_depend_on_the_unit(factor):
    box = _box(20000, 4)
    got = rough_share(torch.from_numpy(box * factor), 0.03 * factor)
    assert got == pytest.approx(rough_share(torch.from_numpy(box), 0.03), abs=0.02)


def test_rough_share_against_the_surface_variation_worked_by_hand():
    # a 5 x 5 grid of step 1 with its middle point lifted by 3: every query's neighbourhood
    # is all 25 points (within 8 voxels of 1); variances 2, 2 (x, y) and
    # 9 / 25 - (3 / 25)^2 = 0.3456 (z), no covariance: variation 0.3456 / 4.3456 = 0.0795
    xy = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0)), -1).reshape(-1, 2)
    z = np.zeros(25)
    z[12] = 3.0
    pts = np.column_stack([xy, z])
    cov = np.cov(pts.T, bias=True)
    variation = np.linalg.eigvalsh(cov)[0] / np.trace(cov)
    assert variation == pytest.approx(0.3456 / 4.3456)
    assert rough_share(torch.from_numpy(pts), 1.0, samples=25) == 1.0
    assert rough_share(torch.from_numpy(np.column_stack([xy, np.zeros(25)])), 1.0) == 0.0


def test_rough_share_of_degenerate_clouds():
    assert rough_share(torch.zeros(0, 3), 0.1) == 0.0
    few = torch.from_numpy(_surface(LINE_MIN_POINTS - 1, 11))
    assert rough_share(few, 0.01) == 0.0
    with pytest.raises(ShapeError):
        rough_share(torch.zeros(4, 2), 0.1)
    with pytest.raises(ShapeError):
        rough_share(torch.zeros(4, 3), -1.0)
