"""The registration recipe: every setting of one pairwise registration, in one tree.

A :class:`RegistrationRecipe` holds what ``byoc register`` does to a pair: the features
(kind, weights, voxel), the matching (points per cloud, ratio-test matches per direction),
the robust fit (estimator, its iterations and thresholds), the refinement and the confidence
gate. :data:`PRESETS` holds one recipe per feature type, chosen by measurement
(docs/registering.md, "Defaults for learned features"); every default of the tool's
pairwise registration is stated here once, and the commands' options, their help, the
Python API, the evaluation methods and the self-posed pairs read it from here.

A recipe is a TOML file (:func:`load_recipe`, :func:`recipe_to_toml`): an optional
``preset = "byoc"`` (or ``"fpfh"``) and tables that change its fields::

    preset = "byoc"
    [matching]
    max_points = 3000

The reports of ``register``, ``register-batch``, ``register-scans`` and ``odometry`` carry the
recipe they ran (:meth:`RegistrationRecipe.as_dict`); written back as TOML it runs the same
registration again.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from byoc_cli.limits import CONFIDENCE, MAX_ITERATIONS, NUM_SUBSETS, SUBSET_SIZE
from byoc_cli.pipeline.confidence import DEFAULT_MIN_CONFIDENCE
from byoc_cli.pipeline.recipe_rules import (
    ESTIMATORS,
    FALLBACKS,
    FEATURE_KINDS,
    REFINEMENTS,
    RULES,
    RecipeError,
    check_recipe,
    check_value,
    describe_value,
)

# the fields' choices, rules and error are :mod:`byoc_cli.pipeline.recipe_rules`'s, and read
# from here too
__all__ = [
    "DEFAULT_PRESET",
    "ESTIMATORS",
    "FALLBACKS",
    "FEATURE_KINDS",
    "PAPER",
    "PRESETS",
    "REFINEMENTS",
    "RULES",
    "FeaturesRecipe",
    "FittingRecipe",
    "GateRecipe",
    "MatchingRecipe",
    "RecipeError",
    "RefinementRecipe",
    "RegistrationRecipe",
    "check_recipe",
    "check_value",
    "describe_default",
    "load_recipe",
    "preset",
    "preset_values",
    "recipe_from_dict",
    "recipe_to_toml",
    "with_values",
]


@dataclass(frozen=True)
class FeaturesRecipe:
    """The features of both clouds.

    Attributes:
        kind: ``"byoc"`` (the learned encoder) or ``"fpfh"`` (Open3D FPFH).
        weights: a weights file for byoc (None: the shipped weights).
        voxel: ``"auto"`` (from each pair's clouds, :mod:`byoc_cli.pipeline.scale`),
            ``"own"`` (the features' own voxel, :attr:`reference_voxel`) or a number (in
            the units of the points).
        reference_voxel: the features' own voxel in metres (None: the weights' voxel).
    """

    kind: str
    weights: str | None = None
    voxel: float | str = "auto"
    reference_voxel: float | None = None


@dataclass(frozen=True)
class MatchingRecipe:
    """Ratio-test matching.

    Attributes:
        max_points: seeded random subset of kept points per cloud that enters matching
            (0 = all).
        correspondences: the top-k Lowe-ratio matches kept per direction (2k in all; the
            ratio is each match's weight, no threshold).
        mutual: keep only mutual nearest neighbours before the top-k selection.
        turns: learned features only: when the first result is below 0.95, extract the
            source's features again turned by 60 to 300 deg (every 60) about the up axis and
            keep the most confident (:mod:`byoc_cli.pipeline.turns`). True: also, with any
            features, a result that reaches the gate is checked against its turns about the
            up axis (its confidence capped at 0.1 when one fits what is not floor, ceiling or
            wall better: :mod:`byoc_cli.pipeline.structure_check`). ``"auto"`` (the ``byoc``
            preset): the turned tries alone, where the features see the clouds at their own
            voxel (depth frames, RGB-D fragments).
    """

    max_points: int
    correspondences: int
    mutual: bool = False
    turns: bool | str = False


@dataclass(frozen=True)
class FittingRecipe:
    """The robust fit.

    Attributes:
        estimator: ``"ransac"``, ``"procrustes"`` (randomized weighted Procrustes, the
            paper's section 3.1) or ``"sc2"`` (second-order spatial compatibility).
        inlier_factor: inlier threshold as a multiple of the voxel (RANSAC's threshold, and
            that of the reported inliers and overlap).
        ransac_iterations, ransac_confidence: RANSAC's limits.
        num_subsets, subset_size: randomized Procrustes' candidates and their size.
    """

    estimator: str = "ransac"
    inlier_factor: float = 2.0
    ransac_iterations: int = MAX_ITERATIONS
    ransac_confidence: float = CONFIDENCE
    num_subsets: int = NUM_SUBSETS
    subset_size: int = SUBSET_SIZE


@dataclass(frozen=True)
class RefinementRecipe:
    """The refinement after the robust fit.

    Attributes:
        method: ``"multiscale"`` (:func:`byoc_cli.pipeline.refine.refine_multiscale`:
            coarse-to-fine point-to-plane ICP on the full clouds, degenerate directions held)
            or ``"none"``.
        restarts: after ``"multiscale"``, refine again from starts turned around the result
            and keep the better end (:func:`byoc_cli.pipeline.restarts.restart_refinement`).
    """

    method: str
    restarts: bool = True


@dataclass(frozen=True)
class GateRecipe:
    """The confidence gate.

    Attributes:
        min_confidence: a registration below this calibrated probability of being right is
            flagged (``byoc register`` exits 3).
        fallback: ``"fpfh"``: below the gate, register the pair again with FPFH features and
            keep the more confident result (byoc features only); ``"none"``: never.
        retries: below the gate, match, fit and refine the same features again with up to
            this many next seeds, each retry's confidence discounted for the tries it was
            picked from, and keep the most confident (:mod:`byoc_cli.pipeline.retries`);
            before the fallback. 0: never.
        recheck: a learned result that passes at low overlap is registered once more with
            the next seed, and is ambiguous (does not pass) when that ends elsewhere
            (:mod:`byoc_cli.pipeline.recheck`).
        visibility: a passing result does not pass when it puts a share of one scan where
            the other's sensor, at its cloud's origin, saw empty space
            (:mod:`byoc_cli.pipeline.visibility`).
    """

    min_confidence: float = DEFAULT_MIN_CONFIDENCE
    fallback: str = "none"
    retries: int = 0
    recheck: bool = False
    visibility: bool = False


@dataclass(frozen=True)
class RegistrationRecipe:
    """Every setting of one pairwise registration (module doc).

    Attributes:
        features, matching, fitting, refinement, gate: the stages' settings.
        seed: seeds every random choice (subsets, sampling, RANSAC).
    """

    features: FeaturesRecipe
    matching: MatchingRecipe
    fitting: FittingRecipe
    refinement: RefinementRecipe
    gate: GateRecipe
    seed: int = 0

    def __post_init__(self) -> None:
        check_recipe(self)

    def as_dict(self) -> dict[str, Any]:
        """A JSON-friendly tree (what the reports carry)."""
        return dataclasses.asdict(self)

    def with_kind(self, kind: str) -> RegistrationRecipe:
        """A copy with features of ``kind`` (their own voxel: that preset's), every other
        setting kept."""
        own = preset(kind).features.reference_voxel
        features = dataclasses.replace(self.features, kind=kind, reference_voxel=own)
        return dataclasses.replace(self, features=features)

    def changed(self, **paths: Any) -> RegistrationRecipe:
        """A copy with fields changed, named ``"stage.field"`` with the dot written as
        ``__`` (``changed(matching__max_points=3000, seed=1)``); None values are skipped."""
        return with_values(self, {k.replace("__", "."): v for k, v in paths.items()})


def with_values(recipe: RegistrationRecipe, values: Mapping[str, Any]) -> RegistrationRecipe:
    """A copy of ``recipe`` with the fields named ``"stage.field"`` (or ``"seed"``) set to
    the values of ``values`` (None: unchanged).

    Raises:
        RecipeError: a value out of its range.
    """
    stages: dict[str, dict[str, Any]] = {}
    top: dict[str, Any] = {}
    for path, value in values.items():
        if value is None:
            continue
        stage, _, name = path.partition(".")
        if name:
            stages.setdefault(stage, {})[name] = value
        else:
            top[stage] = value
    for stage, changes in stages.items():
        top[stage] = dataclasses.replace(getattr(recipe, stage), **changes)
    return dataclasses.replace(recipe, **top)


# ------------------------------------------------------------------ presets

#: the recipe of each feature type (``--features``)
PRESETS: dict[str, RegistrationRecipe] = {
    # learned features: RANSAC on the top 2500 ratio-test matches per direction, then
    # coarse-to-fine point-to-plane ICP on the full clouds that holds sliding directions
    # (benchmarks/estimators.py): randomized Procrustes registered a fifth of the development
    # fragments that RANSAC did with the same features; plain ICP slid along the planes of
    # tum_fr3_cabinet. Below the gate, two more seeds (the cut pairs of docs/low-overlap.md:
    # RR 51.0 % -> 60.4 %), then FPFH gives a second opinion (docs/confidence.md).
    "byoc": RegistrationRecipe(
        FeaturesRecipe("byoc"),
        MatchingRecipe(max_points=5000, correspondences=2500, turns="auto"),
        FittingRecipe(),
        RefinementRecipe("multiscale"),
        GateRecipe(fallback="fpfh", retries=2, recheck=True, visibility=True),
    ),
    # Open3D's tutorial voxel for FPFH; RANSAC needs more than the top 200 of noisy FPFH
    # matches; 10000 keeps every point of a 3DMatch fragment at 5 cm (median rotation error
    # 2.9 deg against 4.8 deg with 5000) and bounds the matching cost of larger scans
    "fpfh": RegistrationRecipe(
        FeaturesRecipe("fpfh", reference_voxel=0.05),
        MatchingRecipe(max_points=10000, correspondences=1000),
        FittingRecipe(),
        RefinementRecipe("none"),
        GateRecipe(),
    ),
}
#: the preset of the commands and the API when nothing names one
DEFAULT_PRESET = "byoc"

#: the paper's matching and fit (section 3.1: the top 200 ratio-test matches per direction,
#: randomized Procrustes of 100 subsets of 20, no refinement), the settings of
#: :class:`~byoc_cli.pipeline.register.RegisterConfig` when none are given
PAPER = RegistrationRecipe(
    FeaturesRecipe("byoc"),
    MatchingRecipe(max_points=PRESETS["byoc"].matching.max_points, correspondences=200),
    FittingRecipe(estimator="procrustes"),
    RefinementRecipe("none"),
    GateRecipe(),
)


def preset(kind: str | None = None) -> RegistrationRecipe:
    """The recipe of feature type ``kind`` (None: :data:`DEFAULT_PRESET`).

    Raises:
        RecipeError: an unknown kind.
    """
    kind = DEFAULT_PRESET if kind is None else kind
    if kind not in PRESETS:
        raise RecipeError(f"unknown preset {kind!r} (known: {', '.join(PRESETS)})")
    return PRESETS[kind]


def preset_values(path: str) -> dict[str, Any]:
    """``{kind: value}`` of one field (``"matching.max_points"``, ``"seed"``) per preset."""
    out = {}
    for kind, recipe in PRESETS.items():
        value: Any = recipe
        for name in path.split("."):
            value = getattr(value, name)
        out[kind] = value
    return out


def describe_default(path: str, show=str) -> str:
    """The presets' value of a field as help text: ``"5000 with byoc features, 10000 with
    fpfh"``, or one value when the presets agree (``show`` formats a value)."""
    values = preset_values(path)
    shown = {kind: show(value) for kind, value in values.items()}
    if len(set(shown.values())) == 1:
        return next(iter(shown.values()))
    kinds = list(shown)
    first = f"{shown[kinds[0]]} with {kinds[0]} features"
    return ", ".join([first, *(f"{shown[k]} with {k}" for k in kinds[1:])])


# ------------------------------------------------------------------ TOML

_STAGES = {
    "features": FeaturesRecipe,
    "matching": MatchingRecipe,
    "fitting": FittingRecipe,
    "refinement": RefinementRecipe,
    "gate": GateRecipe,
}


def recipe_from_dict(data: Mapping[str, Any]) -> RegistrationRecipe:
    """The recipe of a TOML-like tree: ``preset`` (default :data:`DEFAULT_PRESET`, or the
    ``features.kind`` given) changed by the tables' fields. Every key and value is checked
    against :data:`RULES` before it is used.

    Raises:
        RecipeError: an unknown table or field, or a value of the wrong type or out of its
            range (the message names the key).
    """
    known = {"preset", "seed", *_STAGES}
    for key in data:
        if key not in known:
            raise RecipeError(
                f"unknown key {describe_value(key)} (known: {', '.join(sorted(known))})"
            )
    values: dict[str, Any] = {}
    for key in ("preset", "seed"):
        if key in data:
            check_value(key, data[key])
            values[key] = data[key]
    for stage, kind_of in _STAGES.items():
        table = data.get(stage, {})
        if not isinstance(table, Mapping):
            raise RecipeError(f"[{stage}] must be a table (got {describe_value(table)})")
        names = [f.name for f in fields(kind_of)]
        for name, value in table.items():
            if name not in names:
                shown = describe_value(name)[1:-1]
                raise RecipeError(f"unknown field {stage}.{shown} (known: {', '.join(names)})")
            check_value(f"{stage}.{name}", value)
            values[f"{stage}.{name}"] = value
    base = preset(values.pop("preset", values.get("features.kind")))
    return with_values(base, values)


def load_recipe(path: str | os.PathLike[str]) -> RegistrationRecipe:
    """Read a recipe from a TOML file (module doc) of at most 64 KiB, nested at most 16 deep,
    keys of at most 8 dotted parts (:func:`byoc_cli.io.tomlfile.read_toml`).

    Raises:
        InputError: the file cannot be read, is not TOML, is too large or too deep, or holds
            an unusable recipe (one line naming the file and the key).
    """
    from byoc_cli.errors import InputError
    from byoc_cli.io.tomlfile import read_toml

    data = read_toml(path, "recipe", "a TOML recipe")
    try:
        return recipe_from_dict(data)
    except RecipeError as exc:
        raise InputError(path, f"recipe: {exc}") from None


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"')
        return f'"{escaped}"'
    return repr(value)


def recipe_to_toml(recipe: RegistrationRecipe | Mapping[str, Any]) -> str:
    """The TOML text of a recipe (or of its :meth:`~RegistrationRecipe.as_dict`); None
    values (the shipped weights, the weights' voxel) are left out: reading it back gives the
    same recipe (:func:`load_recipe`)."""
    tree = recipe.as_dict() if isinstance(recipe, RegistrationRecipe) else dict(recipe)
    lines = [f"seed = {_toml_value(tree['seed'])}"]
    for stage in _STAGES:
        lines += ["", f"[{stage}]"]
        lines += [
            f"{name} = {_toml_value(value)}"
            for name, value in tree[stage].items()
            if value is not None
        ]
    return "\n".join(lines) + "\n"
