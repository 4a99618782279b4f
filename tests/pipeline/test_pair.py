"""One featured pair to a Registration in the input's coordinates (pipeline/pair.py)."""

from __future__ import annotations

import numpy as np

from byoc_cli.pipeline.featurizer import Featurizer
from byoc_cli.pipeline.pair import about_origins, match_pair, same_voxel
from byoc_cli.pipeline.recipe import preset
from tests.pipeline._clouds import cube, moved


def test_about_origins_maps_input_coordinates():
    rng = np.random.default_rng(0)
    c, s = np.cos(0.3), np.sin(0.3)
    T_local = np.eye(4)
    T_local[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T_local[:3, 3] = [0.1, 0.2, -0.3]
    o_src, o_tgt = np.array([4.5e5, 5.2e6, 30.0]), np.array([4.5e5 + 3, 5.2e6 - 1, 31.0])
    x = rng.normal(size=(10, 3)) + o_src
    expected = (x - o_src) @ T_local[:3, :3].T + T_local[:3, 3] + o_tgt
    T = about_origins(T_local, o_src, o_tgt)
    np.testing.assert_allclose(x @ T[:3, :3].T + T[:3, 3], expected, atol=1e-6)
    np.testing.assert_array_equal(about_origins(T_local, None, None), T_local)


def test_match_pair_recovers_a_known_motion_in_the_input_units():
    recipe = preset("fpfh").changed(features__voxel=0.05, refinement__method="multiscale")
    made = Featurizer(recipe, None, "cpu")
    src = cube(2)
    tgt, T = moved(cube(3))
    scale = 1000.0  # millimetres in, points in metres
    f_src = made.extract_points(src, 1 / scale, "source")
    f_tgt = made.extract_points(tgt, 1 / scale, "target")
    got = match_pair(f_src, f_tgt, recipe, None, features="fpfh", weights_sha256=None)
    assert got.features == "fpfh" and got.refine == "multiscale" and got.estimator == "ransac"
    np.testing.assert_allclose(got.T_tgt_src[:3, :3], T[:3, :3], atol=0.05)
    np.testing.assert_allclose(got.T_tgt_src[:3, 3], T[:3, 3] * scale, atol=50)  # mm
    assert got.passed == (got.confidence >= recipe.gate.min_confidence)


def test_same_voxel_leaves_a_pair_at_one_voxel_alone():
    recipe = preset("fpfh").changed(features__voxel=0.05)
    made = Featurizer(recipe, None, "cpu")
    f = made.extract_points(cube(1), None, "cloud")
    assert same_voxel(made, f, f) == (f, f)
