"""The options of the registration recipe (:mod:`byoc_cli.pipeline.recipe`), made from its
presets: every default a command's help shows for them is read from
:data:`~byoc_cli.pipeline.recipe.PRESETS`, never written here.

A command declares the options it takes (:func:`recipe_options`), and :func:`build_recipe`
turns them into one :class:`~byoc_cli.pipeline.recipe.RegistrationRecipe`: the ``--recipe``
file, or the preset of ``--features``, changed by the options given on the command line (an
option left out is None: the recipe's value).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.options import (
    SEED,
    VOXEL,
    VoxelSize,
    apply,
    finite_float,
    float_option,
    int_option,
    path_option,
)
from byoc_cli.pipeline import recheck, visibility
from byoc_cli.pipeline import recipe as recipes


def _default(path: str, show: Callable[[Any], str] = str) -> str:
    return f"[default: {recipes.describe_default(path, show)}]"


#: the recipe option of each name a command may take (in help order)
def _options() -> dict[str, Callable]:
    return {
        "recipe": path_option(
            "--recipe",
            "recipe_path",
            default=None,
            help="A recipe file (TOML: a preset and the settings it changes; "
            "docs/registering.md, Recipes). The options below that are given change it.",
        ),
        "features": click.option(
            "--features",
            type=click.Choice(list(recipes.PRESETS)),
            default=None,
            help="byoc: the learned geometric encoder (the shipped weights, or --weights); "
            f"fpfh: Open3D FPFH. Each has its preset recipe. [default: {recipes.DEFAULT_PRESET}]",
        ),
        "weights": path_option(
            "--weights", default=None, help="Weights file (weights-spec/ format) for byoc."
        ),
        "voxel_size": click.option(
            "--voxel-size",
            type=VoxelSize(),
            default=None,
            help="Feature voxel, in the units of the points. auto: read from the clouds: the "
            f"features' own voxel ({_voxel_own()}) for scans the size of a room or a desk, "
            "scaled with the scan's size outside that range (millimetres, small objects, "
            "LiDAR), and at least 1.8 point spacings of the sparser cloud; the JSON report "
            f"says which and why. A number turns auto off. {_default('features.voxel')}",
        ),
        "fixed_voxel_size": float_option(
            "--voxel-size",
            type=VOXEL,
            default=None,
            help=f"Feature voxel in metres [default: the features' own: {_voxel_own()}].",
        ),
        "estimator": click.option(
            "--estimator",
            type=click.Choice(["auto", *recipes.ESTIMATORS]),
            default=None,
            help="RANSAC, randomized weighted Procrustes (the paper's) or sc2 (second-order "
            "spatial compatibility, for few inliers: docs/low-overlap.md); auto: the recipe's. "
            f"{_default('fitting.estimator')}",
        ),
        "refine": click.option(
            "--refine",
            type=click.Choice(["auto", "none", "multiscale"]),
            default=None,
            help="multiscale: coarse-to-fine point-to-plane ICP on the full clouds that holds "
            "directions the geometry leaves free; none: the robust fit as it is; auto: the "
            f"recipe's. {_default('refinement.method')}",
        ),
        "max_points": int_option(
            "--max-points",
            max=_high("matching.max_points"),
            default=None,
            help="Seeded random subset of kept points per cloud that enters matching (0 = all) "
            f"{_default('matching.max_points')}.",
        ),
        "num_correspondences": int_option(
            "--num-correspondences",
            min=int(recipes.RULES["matching.correspondences"].low),
            max=_high("matching.correspondences"),
            default=None,
            help=f"Top-k ratio-test matches kept per direction "
            f"{_default('matching.correspondences')}.",
        ),
        "min_confidence": float_option(
            "--min-confidence",
            type=finite_float(0, 1),
            default=None,
            help="Exit 3 when the confidence, the calibrated probability that T is right, is "
            "below this (the default keeps 95 % of the right results of the development pairs, "
            f"docs/confidence.md; 0 accepts every result) {_default('gate.min_confidence')}.",
        ),
        "fallback": click.option(
            "--fallback",
            type=click.Choice(list(recipes.FALLBACKS)),
            default=None,
            help="With byoc features: when the confidence is below --min-confidence, register "
            "the pair again with FPFH features (same scale, same refinement) and keep the more "
            "confident result; the report says which ran (docs/confidence.md). none: never. "
            f"{_default('gate.fallback')}",
        ),
        "retries": int_option(
            "--retries",
            min=0,
            max=_high("gate.retries"),
            default=None,
            help="When the confidence is below --min-confidence, match and fit the same "
            "features again with up to this many next seeds, each retry's confidence "
            "discounted for the tries it was picked from, and keep the most confident (before "
            "the FPFH fallback; docs/low-overlap.md). 0: never. "
            f"{_default('gate.retries')}",
        ),
        "recheck": click.option(
            "--recheck/--no-recheck",
            default=None,
            help="With byoc features: when the result passes with an estimated overlap below "
            f"{recheck.BELOW_OVERLAP:g}, match and fit the same features once more with the next "
            f"seed; when that ends elsewhere at confidence {recheck.RIVAL_FLOOR:g} or more, the "
            "result is ambiguous and exits 3, "
            "and the report lists both poses (docs/low-overlap.md). "
            f"{_default('gate.recheck')}",
        ),
        "visibility": click.option(
            "--visibility/--no-visibility",
            default=None,
            help="With byoc features at their own voxel: a result that passes exits 3 when "
            f"more than {visibility.MAX_FREE_SPACE:g} of either cloud lies, under T, in space "
            "the other's sensor saw empty; each sensor is taken at its cloud's origin (depth "
            "frames, 3DMatch fragments, scans in their scanner's frame). --no-visibility for "
            "clouds moved out of their sensors' frames (docs/low-overlap.md). "
            f"{_default('gate.visibility')}",
        ),
        "turns": click.option(
            "--turns/--no-turns",
            default=None,
            help="With byoc features: when the confidence is below 0.95, extract the source's "
            "features again turned by 60 to 300 deg (every 60) about the up axis (the "
            "source's tilted onto the target's) and keep the most confident result; a result "
            "that fits as well turned elsewhere exits 3 as ambiguous. The flag also turns a "
            "result that passes 90, 180 and 270 deg, with any features, and it exits 3 as "
            "ambiguous when a turn fits what is not floor, ceiling or wall as well. For scans "
            "turned far apart about the vertical (terrestrial scanner stations, turntables): "
            "docs/registering.md, Turned scans. The byoc preset's auto: the turned tries "
            "alone, below 0.85, where the features see the clouds at their own voxel (depth "
            f"frames, RGB-D fragments). {_default('matching.turns')}",
        ),
        "seed": click.option(
            "--seed",
            type=SEED,
            default=None,
            help=f"Seeds every random choice; the same seed gives the same result. "
            f"{_default('seed')}",
        ),
    }


def _high(path: str) -> int:
    """The largest value of an integer field of the recipe (:data:`recipes.RULES`)."""
    return int(recipes.RULES[path].high)


def _voxel_own() -> str:
    own = recipes.preset_values("features.reference_voxel")
    shown = {k: "the weights' voxel" if v is None else f"{v:g} m" for k, v in own.items()}
    return ", ".join(f"{text} for {kind}" for kind, text in shown.items())


#: the option names of :func:`build_recipe` and the recipe field each one changes
FIELDS = {
    "features": "features.kind",
    "weights": "features.weights",
    "voxel_size": "features.voxel",
    "estimator": "fitting.estimator",
    "refine": "refinement.method",
    "max_points": "matching.max_points",
    "num_correspondences": "matching.correspondences",
    "min_confidence": "gate.min_confidence",
    "fallback": "gate.fallback",
    "retries": "gate.retries",
    "recheck": "gate.recheck",
    "visibility": "gate.visibility",
    "turns": "matching.turns",
    "seed": "seed",
}


def recipe_options(*names: str) -> Callable:
    """The decorator of the recipe options ``names`` (keys of :data:`FIELDS`, ``"recipe"``,
    or ``"fixed_voxel_size"``: ``--voxel-size`` in metres without auto)."""
    made = _options()
    return apply(*(made[name] for name in names))


#: every recipe option of a pairwise registration (``register``, ``register-batch``)
PAIRWISE = (
    "recipe",
    "features",
    "weights",
    "voxel_size",
    "estimator",
    "refine",
    "max_points",
    "num_correspondences",
    "min_confidence",
    "fallback",
    "retries",
    "recheck",
    "visibility",
    "turns",
    "seed",
)


def build_recipe(options: dict[str, Any]) -> recipes.RegistrationRecipe:
    """The recipe of a command's options; the recipe options are taken out of ``options``.

    ``recipe_path`` (``--recipe``) or the preset of ``features`` is the base; every other
    option given (not None, not ``auto`` for ``--estimator`` and ``--refine``) changes it.

    Raises:
        InputError: the ``--recipe`` file cannot be read or holds an unusable recipe.
        click.BadParameter: an option that does not go with the recipe.
    """

    path: Path | None = options.pop("recipe_path", None)
    given = {name: options.pop(name) for name in list(options) if name in FIELDS}
    if path is not None:
        base = recipes.load_recipe(path)
    else:
        base = recipes.preset(given.get("features"))
    if given.get("features") is not None and given["features"] != base.features.kind:
        base = base.with_kind(given["features"])
    for name in ("estimator", "refine"):
        if given.get(name) == "auto":
            given[name] = None
    given.pop("features", None)
    if given.get("weights") is not None:
        given["weights"] = str(given["weights"])
    changes = {FIELDS[name]: value for name, value in given.items()}
    try:
        recipe = recipes.with_values(base, changes)
    except recipes.RecipeError as exc:
        raise click.BadParameter(str(exc)) from None
    if recipe.features.kind != "byoc" and recipe.gate.fallback != "none":
        recipe = recipe.changed(gate__fallback="none")  # the fallback is for learned features
    return recipe
