"""The registration recipe: presets, checks, TOML in and out, its RegisterConfig."""

from __future__ import annotations

import dataclasses

import pytest

from byoc_cli.errors import InputError
from byoc_cli.pipeline.recipe import (
    PAPER,
    PRESETS,
    RecipeError,
    describe_default,
    load_recipe,
    preset,
    preset_values,
    recipe_from_dict,
    recipe_to_toml,
)
from byoc_cli.pipeline.register import RegisterConfig, register_config


@pytest.mark.parametrize("kind", sorted(PRESETS))
def test_a_preset_survives_toml(kind, tmp_path):
    path = tmp_path / "r.toml"
    path.write_text(recipe_to_toml(PRESETS[kind]))
    assert load_recipe(path) == PRESETS[kind]
    assert load_recipe(path).features.kind == kind


def test_a_changed_recipe_survives_toml_and_its_report_form(tmp_path):
    recipe = PRESETS["byoc"].changed(
        matching__max_points=3000, fitting__estimator="procrustes", seed=7
    )
    recipe = recipe.changed(features__weights="w.safetensors", features__voxel=0.03)
    path = tmp_path / "r.toml"
    path.write_text(recipe_to_toml(recipe.as_dict()))  # what a report carries
    assert load_recipe(path) == recipe


def test_a_file_names_the_preset_and_changes_some_fields(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text('preset = "fpfh"\n[matching]\nmax_points = 123\n')
    got = load_recipe(path)
    assert got.features.kind == "fpfh" and got.matching.max_points == 123
    assert got.fitting == PRESETS["fpfh"].fitting
    assert got.matching.correspondences == PRESETS["fpfh"].matching.correspondences
    path.write_text("")
    assert load_recipe(path) == preset()


def test_a_file_may_name_the_sc2_estimator_and_the_config_carries_it(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text('[fitting]\nestimator = "sc2"\n')
    got = load_recipe(path)
    assert got.fitting.estimator == "sc2"
    assert register_config(got).estimator == "sc2"
    assert PRESETS["byoc"].fitting.estimator == PRESETS["fpfh"].fitting.estimator == "ransac"


def test_turns_take_auto_true_or_false_and_only_true_checks_the_structure(tmp_path):
    assert PRESETS["byoc"].matching.turns == "auto" and PRESETS["fpfh"].matching.turns is False
    assert register_config(PRESETS["byoc"]).structure_check is False
    path = tmp_path / "r.toml"
    for text, value in (("true", True), ("false", False), ('"auto"', "auto")):
        path.write_text(f"[matching]\nturns = {text}\n")
        got = load_recipe(path)
        assert got.matching.turns == value
        assert register_config(got).structure_check is (value is True)
        path.write_text(recipe_to_toml(got))
        assert load_recipe(path) == got
    path.write_text('[matching]\nturns = "always"\n')
    with pytest.raises(InputError, match=r"matching\.turns"):
        load_recipe(path)


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("[matching]\nmax_points = -1\n", "matching.max_points"),
        ("[matching]\nmax_pts = 1\n", "unknown field matching.max_pts"),
        ("[nope]\n", "unknown key 'nope'"),
        ('preset = "sift"\n', "preset must be one of byoc, fpfh (got 'sift')"),
        ('[fitting]\nestimator = "lmeds"\n', "fitting.estimator"),
        ("[gate]\nmin_confidence = 1.5\n", "gate.min_confidence"),
        ('[features]\nvoxel = "big"\n', "features.voxel"),
        ("[matching\n", "is not a TOML recipe"),
        ("matching = 3\n", "[matching] must be a table"),
        ("seed = -1\n", "seed"),
    ],
)
def test_a_bad_recipe_file_is_an_input_error_naming_it(tmp_path, text, problem):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(InputError) as caught:
        load_recipe(path)
    assert str(caught.value).startswith(f"{path}: ") and problem in str(caught.value)
    assert "\n" not in str(caught.value)


def test_a_missing_recipe_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match=r"none\.toml"):
        load_recipe(tmp_path / "none.toml")


def test_the_removed_refinement_icp_is_refused_by_name():
    with pytest.raises(RecipeError, match=r"refinement\.method.*none, multiscale"):
        recipe_from_dict({"refinement": {"method": "icp"}})


def test_values_out_of_range_are_refused_in_code_too():
    with pytest.raises(RecipeError, match=r"matching\.correspondences"):
        PRESETS["byoc"].changed(matching__correspondences=2)
    with pytest.raises(RecipeError, match=r"refinement\.method"):
        PRESETS["byoc"].changed(refinement__method="plain")
    with pytest.raises(RecipeError, match="unknown preset"):
        preset("sift")


@pytest.mark.parametrize("kind", sorted(PRESETS))
def test_register_config_carries_every_setting_of_the_recipe(kind):
    recipe = PRESETS[kind].changed(seed=5)
    config = register_config(recipe)
    fit = recipe.fitting
    assert (config.num_correspondences, config.max_points) == (
        recipe.matching.correspondences,
        recipe.matching.max_points,
    )
    assert (config.estimator, config.num_subsets, config.subset_size) == (
        fit.estimator,
        fit.num_subsets,
        fit.subset_size,
    )
    assert (config.inlier_factor, config.ransac_iterations, config.ransac_confidence) == (
        fit.inlier_factor,
        fit.ransac_iterations,
        fit.ransac_confidence,
    )
    method = recipe.refinement.method
    assert config.refine == (None if method == "none" else method)
    assert register_config(recipe, refine=False).refine is None
    assert (config.seed, config.confidence_model) == (5, kind)


def test_register_config_defaults_are_the_papers():
    assert RegisterConfig() == dataclasses.replace(register_config(PAPER), confidence_model="byoc")


def test_help_text_of_a_default_names_each_preset_when_they_differ():
    values = preset_values("matching.max_points")
    assert set(values) == set(PRESETS)
    text = describe_default("matching.max_points")
    for kind, value in values.items():
        assert f"{value} with {kind}" in text
    same = preset_values("fitting.ransac_iterations")
    assert describe_default("fitting.ransac_iterations") == str(same["byoc"])


def test_every_field_of_a_recipe_has_one_rule():
    from byoc_cli.pipeline.recipe import _STAGES, RULES

    paths = {
        f"{stage}.{f.name}" for stage, kind in _STAGES.items() for f in dataclasses.fields(kind)
    }
    assert set(RULES) == paths | {"seed", "preset"}


@pytest.mark.parametrize(
    ("tree", "problem"),
    [
        ({"preset": ["byoc"]}, "preset must be one of byoc, fpfh (got an array)"),
        ({"features": {"kind": {"a": 1}}}, "features.kind must be one of byoc, fpfh (got a table)"),
        (
            {"fitting": {"num_subsets": 2**63 - 1}},
            "fitting.num_subsets must be an integer in [1, 10000] (got an integer of 19 digits)",
        ),
        ({"fitting": {"subset_size": 2**63 - 1}}, "fitting.subset_size must be an integer in [3,"),
        (
            {"fitting": {"inlier_factor": 1e308}},
            "fitting.inlier_factor must be a number in (0, 100]",
        ),
        ({"fitting": {"inlier_factor": float("inf")}}, "fitting.inlier_factor must be a number"),
        ({"matching": {"max_points": 2.5}}, "matching.max_points must be an integer"),
        ({"matching": {"max_points": True}}, "matching.max_points must be an integer"),
        ({"matching": {"correspondences": 2**40}}, "matching.correspondences must be an integer"),
        ({"fitting": {"ransac_iterations": 10**9}}, "fitting.ransac_iterations must be an integer"),
        ({"refinement": {"restarts": 1}}, "refinement.restarts must be true or false (got 1)"),
        ({"features": {"weights": ["w"]}}, "features.weights must be a file name (got an array)"),
        ({"features": {"voxel": 1e300}}, 'features.voxel must be "auto" or "own" or a number'),
        ({"seed": 2**64}, "seed must be an integer in [0, 18446744073709551615]"),
        ({"gate": []}, "[gate] must be a table (got an array)"),
    ],
)
def test_every_value_is_checked_for_type_and_range_before_use(tree, problem):
    with pytest.raises(RecipeError) as caught:
        recipe_from_dict(tree)
    assert str(caught.value).startswith(problem), str(caught.value)


def test_the_largest_values_in_range_are_taken():
    from byoc_cli import limits

    tree = {
        "fitting": {
            "num_subsets": limits.MAX_NUM_SUBSETS,
            "subset_size": limits.MAX_SUBSET_SIZE,
            "inlier_factor": limits.MAX_INLIER_FACTOR,
        },
        "seed": 2**64 - 1,
    }
    got = recipe_from_dict(tree)
    assert got.fitting.num_subsets == limits.MAX_NUM_SUBSETS and got.seed == 2**64 - 1
