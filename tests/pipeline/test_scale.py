"""The auto voxel: trained range kept, other sizes scaled, density floor, refusals."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from byoc_cli.errors import RegistrationError
from byoc_cli.pipeline.scale import (
    CENTRE_RADIUS,
    DENSITY_FACTOR,
    MISMATCH_FACTOR,
    TRAINED_RADIUS,
    CloudScale,
    choose_voxel,
    measure,
    trained_scale,
)

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
    unlike = choose_voxel((CloudScale(1000, 0.03, 1.0), CloudScale(4000, 0.015, 1.0)), REF)
    assert unlike.voxel_size == pytest.approx(MISMATCH_FACTOR * 0.03)
    assert "sampled unlike" in unlike.reason


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
