"""The auto voxel: trained range kept, other sizes scaled, density floor, scan lines washed
out, refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from byoc_cli.errors import RegistrationError
from byoc_cli.geometry.sampling import linear_share
from byoc_cli.pipeline.scale import (
    CENTRE_RADIUS,
    DENSITY_FACTOR,
    LINE_FREE_SHARE,
    LINE_STEP,
    MAX_LINE_VOXEL,
    TRAINED_RADIUS,
    CloudScale,
    choose_voxel,
    measure,
    scan_line_voxel,
    size_radius,
    trained_scale,
)
from tests._rings import camera_scan, ring_scan, room_scan

REF = 0.025


def test_room_sized_scans_keep_the_reference_voxel():
    for radius in (TRAINED_RADIUS[0], 1.0, TRAINED_RADIUS[1]):
        got = choose_voxel((CloudScale(10_000, 0.005, radius),) * 2, REF)
        assert got.voxel_size == REF and got.refine_voxel == REF and got.factor == 1.0
        assert "trained range" in got.reason


@pytest.mark.parametrize("factor", [0.001, 0.01, 10.0, 100.0])
def test_other_sizes_scale_with_the_data(factor):
    base = CloudScale(10_000, 0.005, CENTRE_RADIUS)
    scaled = CloudScale(10_000, 0.005 * factor, CENTRE_RADIUS * factor)
    assert choose_voxel((base, base), REF).voxel_size == REF
    got = choose_voxel((scaled, scaled), REF)
    assert got.voxel_size == pytest.approx(REF * factor)
    assert "scaled" in got.reason


@pytest.mark.parametrize("factor", [0.001, 0.01, 10.0, 100.0])
def test_trained_scale_brings_other_sizes_to_the_centre_radius(factor):
    """Multiplying by the trained scale makes the refinement voxel the reference one: the
    radius of the scaled data is CENTRE_RADIUS, whatever the density floor did."""
    sparse = CloudScale(1000, 0.05 * factor, CENTRE_RADIUS * factor)
    choice = choose_voxel((sparse, sparse), REF)
    s = trained_scale(choice)
    assert s == pytest.approx(1.0 / factor)
    assert choice.refine_voxel * s == pytest.approx(REF)
    in_range = choose_voxel((CloudScale(10_000, 0.005, 1.0),) * 2, REF)
    assert trained_scale(in_range) is None
    raised = choose_voxel((CloudScale(1000, 0.03, 1.0),) * 2, REF)  # density floor only
    assert trained_scale(raised) is None


def test_sparse_clouds_raise_the_feature_voxel_but_not_the_refinement():
    alike = choose_voxel((CloudScale(1000, 0.03, 1.0), CloudScale(1000, 0.03, 1.0)), REF)
    assert alike.voxel_size == pytest.approx(DENSITY_FACTOR * 0.03)
    assert alike.refine_voxel == REF
    assert alike.keep == (1.0, 1.0)
    unlike = choose_voxel((CloudScale(1000, 0.03, 1.0), CloudScale(4000, 0.015, 1.0)), REF)
    assert unlike.voxel_size == pytest.approx(DENSITY_FACTOR * 0.03)
    # the denser cloud's features come from a quarter of its points: the spacing doubles
    assert unlike.keep == pytest.approx((1.0, 0.25))
    assert unlike.keep_of(1) == pytest.approx(0.25) and unlike.keep_of(5) == 1.0
    assert "as sparse as the other" in unlike.reason
    assert unlike.as_dict()["feature_points_kept"] == pytest.approx([1.0, 0.25])


def test_as_dict_is_json_ready():
    import json

    got = choose_voxel((CloudScale(10, 0.01, 0.5),), REF).as_dict()
    assert json.loads(json.dumps(got))["clouds"][0]["radius"] == 0.5


def test_no_extent_is_refused():
    with pytest.raises(RegistrationError, match="no extent"):
        choose_voxel((CloudScale(100, 0.5, 0.6),), REF)
    with pytest.raises(RegistrationError, match="no extent"):
        choose_voxel((CloudScale(100, 0.0, 0.0),), REF)


def test_measure_refuses_too_few_points():
    with pytest.raises(RegistrationError, match="src: only 3 distinct"):
        measure(torch.rand(3, 3, dtype=torch.float64), "src")
    with pytest.raises(RegistrationError, match="only 1 distinct"):
        measure(torch.ones(200, 3, dtype=torch.float64))
    pts = torch.from_numpy(np.random.default_rng(0).uniform(0, 1, (500, 3)))
    got = measure(pts)
    assert got.num_points == 500 and got.spacing > 0 and got.radius > 0


def test_points_that_fill_a_volume_are_refused_and_surfaces_are_not():
    rng = np.random.default_rng(0)
    noise = measure(torch.from_numpy(rng.uniform(0, 3, (20000, 3))), "noise.ply")
    xy = rng.uniform(0, 3, (20000, 2))
    plane = measure(torch.from_numpy(np.column_stack([xy, np.zeros(len(xy))])), "plane.ply")
    assert noise.dimension > 2.9 and 1.9 < plane.dimension < 2.2
    with pytest.raises(RegistrationError, match=r"noise\.ply: the points fill a volume"):
        choose_voxel((plane, noise), REF)
    choose_voxel((plane, plane), REF)


def _lines(gap: float, step: float = 0.01, size: float = 4.0) -> torch.Tensor:
    x, y = np.meshgrid(np.arange(0.0, size, step), np.arange(0.0, size, gap))
    return torch.from_numpy(np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]))


def test_a_ring_scan_is_flagged_and_a_camera_scan_of_the_same_scene_is_not():
    rings = measure(torch.from_numpy(ring_scan()), "rings.ply")
    camera = measure(torch.from_numpy(camera_scan()), "camera.ply")
    assert rings.line_voxel > 0 and camera.line_voxel == 0.0
    # the toy scene is mostly open ground: its far rings stay lines up to the cap
    assert rings.line_voxel == pytest.approx(MAX_LINE_VOXEL * rings.radius)
    assert rings.line_voxel > 10 * rings.spacing


def test_lines_wash_out_at_the_first_step_that_reaches_across_them():
    lines = _lines(0.5)
    got = measure(lines)
    assert got.spacing == pytest.approx(0.01, rel=1e-6)
    # the steps from the density voxel: the first whose neighbourhood (2.5 voxels) spans 0.5
    steps = DENSITY_FACTOR * got.spacing * LINE_STEP ** np.arange(1, 12)
    first = steps[np.argmax(2.5 * steps > 0.5)]
    assert got.line_voxel == pytest.approx(first)
    assert linear_share(lines, got.line_voxel) <= LINE_FREE_SHARE
    assert linear_share(lines, got.line_voxel / LINE_STEP) > LINE_FREE_SHARE


def test_an_evenly_sampled_surface_has_no_line_voxel():
    xy = np.random.default_rng(3).uniform(0, 3, (20000, 2))
    plane = torch.from_numpy(np.column_stack([xy, 0.1 * np.sin(2 * xy[:, 0])]))
    got = measure(plane)
    assert got.line_voxel == 0.0
    assert scan_line_voxel(plane, got.spacing, got.radius) == 0.0
    assert scan_line_voxel(plane, 0.0, got.radius) == 0.0


@pytest.mark.parametrize("factor", [0.001, 1000.0])
def test_the_line_voxel_scales_with_the_units(factor):
    lines = _lines(0.5)
    assert measure(lines * factor).line_voxel == pytest.approx(
        measure(lines).line_voxel * factor, rel=1e-9
    )


def test_scan_lines_raise_the_feature_voxel_but_not_the_refinement():
    rings = measure(torch.from_numpy(ring_scan()), "rings.ply")
    even = rings._replace(line_voxel=0.0)
    got = choose_voxel((rings, even), REF)
    before = choose_voxel((even, even), REF)
    assert got.voxel_size == pytest.approx(rings.line_voxel) and got.voxel_size > before.voxel_size
    assert got.refine_voxel == before.refine_voxel
    assert got.scan_lines and not before.scan_lines
    assert "scan lines" in got.reason and "scan lines" not in before.reason
    import json

    clouds = json.loads(json.dumps(got.as_dict()))["clouds"]
    assert clouds[0]["line_voxel"] == pytest.approx(rings.line_voxel)
    assert clouds[1]["line_voxel"] == 0.0


def test_a_line_voxel_below_the_chosen_voxel_changes_nothing():
    scale = CloudScale(10_000, 0.005, 1.0)
    fine_lines = scale._replace(line_voxel=0.01)
    assert choose_voxel((fine_lines,), REF).voxel_size == REF
    assert choose_voxel((fine_lines,), REF).scan_lines


def test_fpfh_sizes_a_laser_scanned_room_by_its_even_radius():
    """Raw radius 1.4 (in the trained range: the points crowd near the scanner), 2.4 thinned
    evenly: FPFH's voxel scales with 2.4, the learned features' stays."""
    room = (CloudScale(200_000, 0.005, 1.4, even_radius=2.4),) * 2
    assert choose_voxel(room, 0.05).voxel_size == 0.05
    fpfh = choose_voxel(room, 0.05, even=True)
    assert fpfh.voxel_size == pytest.approx(0.05 * 2.4 / CENTRE_RADIUS)
    assert fpfh.refine_voxel == 0.05  # the refinement keeps the voxel of the raw radius
    assert "radius 1.4 is in the trained range" in fpfh.reason
    assert "features at 2.4, the radius thinned evenly" in fpfh.reason
    assert size_radius(room) == 2.4


@pytest.mark.parametrize(
    ("radius", "even", "size"),
    [(1.0, 1.1, 1.0), (1.0, None, 1.0), (0.05, 0.06, 0.05), (2.0, 1.9, 2.0), (2.0, 2.5, 2.5)],
)
def test_only_an_even_radius_above_the_trained_range_and_the_raw_one_sizes_fpfh(radius, even, size):
    """Fragments and depth frames (in the range both ways) and objects (scaled down) keep
    their radius; a LiDAR scan larger either way takes the larger."""
    scales = (CloudScale(10_000, 0.001, radius, even_radius=even),)
    assert size_radius(scales) == size
    assert (
        choose_voxel(scales, REF, even=True).voxel_size
        == choose_voxel((scales[0]._replace(radius=size),), REF).voxel_size
    )


def _mm_object(**changes):
    scale = CloudScale(80_000, 0.4, 50.0, origin_radii=9.0, spacing_spread=1.6)
    return scale._replace(**changes)


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({}, True),  # a 10 cm object in millimetres, its scanner 45 cm away
        ({"radius": 9.0}, False),  # below 1 cm in millimetres: a 9 m room in metres
        ({"radius": 150.0}, False),  # 15 cm in millimetres: the trained range
        ({"origin_radii": 2.5}, False),  # a depth frame or fragment (in centimetres)
        ({"origin_radii": 0.2}, False),  # a LiDAR scan about its sensor
        ({"origin_radii": 1e4}, False),  # georeferenced: no sensor at the origin
        ({"origin_radii": None}, False),  # not measured
        ({"even_radius": 60.0}, False),  # a panorama: a terrestrial laser scan
        ({"spacing_spread": 5.2}, False),  # the step grows with the range: a LiDAR street
        ({"spacing_spread": None}, False),  # not measured
        ({"line_voxel": 1.2}, False),  # sampled along lines: a spinning LiDAR's rings
    ],
)
def test_an_object_in_millimetres_is_sized_as_one_and_seen_from_outside(changes, expected):
    from byoc_cli.pipeline.scale import object_in_millimetres

    assert object_in_millimetres((_mm_object(), _mm_object(**changes))) == expected
    assert not object_in_millimetres(())


def test_measure_reads_how_far_the_sensor_stood_in_radii():
    points = camera_scan()
    got = measure(torch.from_numpy(points), lines=False)
    centre = np.median(points, axis=0)
    assert got.origin_radii == pytest.approx(np.linalg.norm(centre) / got.radius)
    moved = measure(torch.from_numpy(points - centre), lines=False)  # about its median
    assert moved.origin_radii == pytest.approx(0.0, abs=1e-9)
    assert json.loads(json.dumps(got._asdict()))["origin_radii"] == got.origin_radii
    assert got.spacing_spread >= 1.0


def test_measure_reads_the_even_radius_of_a_panorama_only():
    room = measure(torch.from_numpy(room_scan()), lines=False)
    assert room.even_radius > 1.3 * room.radius
    assert measure(torch.from_numpy(camera_scan()), lines=False).even_radius is None


def test_a_georeferenced_scan_is_a_panorama_about_its_median():
    """Far from the origin (UTM-like coordinates) the panorama test reads the directions
    about the cloud's median: a room scan moved there is a panorama as at home, a depth frame
    and a LiDAR ring scan are not; near the origin nothing changes (the room's median seen
    from a corner is no panorama)."""
    utm = np.array([4.5e5, 5.2e6, 100.0])
    room = room_scan()
    home = measure(torch.from_numpy(room), lines=False)
    far = measure(torch.from_numpy(room + utm), lines=False)
    assert far.even_radius == pytest.approx(home.even_radius, rel=1e-3)
    for cloud in (camera_scan(), ring_scan()):
        assert measure(torch.from_numpy(cloud + utm), lines=False).even_radius is None
    corner = room - room.min(axis=0)  # the origin at a corner, 0 to 7 m: not far
    assert measure(torch.from_numpy(corner), lines=False).even_radius is None
