"""A registrar's recipe from its arguments (pipeline/engine_recipe.py)."""

from __future__ import annotations

import pytest

from byoc_cli.pipeline.engine_recipe import FROM_RECIPE, registrar_recipe, resolve_device
from byoc_cli.pipeline.recipe import preset


def _recipe(**kw):
    args = {
        "recipe": None,
        "features": None,
        "weights": None,
        "voxel_size": FROM_RECIPE,
        "fallback": "auto",
        "fallback_below": None,
    }
    return registrar_recipe(**{**args, **kw})


def test_no_argument_gives_the_default_preset():
    assert _recipe().as_dict() == preset(None).as_dict()


def test_the_arguments_given_change_the_recipe():
    made = _recipe(voxel_size=0.1, fallback=None, fallback_below=0.3, weights="w.safetensors")
    assert made.features.voxel == 0.1
    assert made.gate.fallback == "none" and made.gate.min_confidence == 0.3
    assert made.features.weights == "w.safetensors"
    assert _recipe(voxel_size=None).features.voxel == "own"
    assert _recipe(features="fpfh").features.kind == "fpfh"
    assert _recipe(features="fpfh").gate.fallback == "none"  # auto: no fallback for fpfh


def test_a_recipe_of_another_kind_is_turned_into_the_features_asked_for():
    made = _recipe(recipe=preset("fpfh"), features="byoc")
    assert made.features.kind == "byoc"


@pytest.mark.parametrize(
    ("kw", "match"),
    [({"features": "sift"}, "features must be one of"), ({"fallback": "icp"}, "fallback")],
)
def test_unknown_values_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        _recipe(**kw)


def test_fpfh_features_have_no_fpfh_fallback():
    with pytest.raises(ValueError, match="fallback"):
        _recipe(features="fpfh", fallback="fpfh")


def test_devices():
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") in ("cpu", "cuda")
    with pytest.raises(ValueError, match="device"):
        resolve_device("tpu")
