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
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from byoc_cli import limits
from byoc_cli.limits import CONFIDENCE, MAX_ITERATIONS, NUM_SUBSETS, SUBSET_SIZE
from byoc_cli.pipeline.confidence import DEFAULT_MIN_CONFIDENCE

#: feature types
FEATURE_KINDS = ("byoc", "fpfh")
#: robust estimators (``sc2``: second-order spatial compatibility, fitting/compatibility.py)
ESTIMATORS = ("procrustes", "ransac", "sc2")
#: refinements after the robust fit
REFINEMENTS = ("none", "multiscale")
#: what runs below the gate
FALLBACKS = ("none", "fpfh")


class RecipeError(ValueError):
    """A recipe (a file, a table, a value) that cannot be used; the message says why."""


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
    """

    max_points: int
    correspondences: int
    mutual: bool = False


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
    """

    min_confidence: float = DEFAULT_MIN_CONFIDENCE
    fallback: str = "none"


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


# ------------------------------------------------------------------ checks


@dataclass(frozen=True)
class FieldRule:
    """What one field of a recipe accepts: its type and range, the one place both are said.

    Attributes:
        kind: ``"int"``, ``"number"`` (finite int or float, not bool), ``"bool"``,
            ``"choice"`` (one of ``words``) or ``"text"`` (a string of at most ``high``
            characters).
        low, high: the closed range of an int or a number (a text: its longest length).
        low_open: ``low`` itself is refused.
        words: the strings a choice takes, or that a number also takes (``"auto"``).
        optional: None is accepted (the shipped weights, the weights' voxel).
    """

    kind: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    words: tuple[str, ...] = ()
    optional: bool = False

    def accepts(self, value: Any) -> bool:
        """Whether ``value`` (from code or from a TOML tree: any type) is in the field's range."""
        if value is None:
            return self.optional
        if isinstance(value, str) and value in self.words:
            return True
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind == "text":
            return isinstance(value, str) and 0 < len(value) <= (self.high or 4096)
        if self.kind == "int" and not _is_int(value):
            return False
        if self.kind in ("int", "number") and _is_number(value):
            above = value > self.low if self.low_open else value >= self.low
            return above and value <= self.high
        return False

    def expected(self) -> str:
        """What the field takes, as the end of ``"<field> must be ..."``."""
        if self.kind == "choice":
            return f"one of {', '.join(self.words)}"
        if self.kind == "bool":
            return "true or false"
        if self.kind == "text":
            return "a file name"
        show = (lambda v: str(int(v))) if self.kind == "int" else (lambda v: f"{v:g}")
        low = f"({show(self.low)}" if self.low_open else f"[{show(self.low)}"
        what = "an integer" if self.kind == "int" else "a number"
        words = " or ".join(f'"{w}"' for w in self.words)
        return f"{words + ' or ' if words else ''}{what} in {low}, {show(self.high)}]"


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


#: the rule of every field of a recipe (``"stage.field"``, ``"seed"``) and of a file's
#: ``preset``: a recipe in code (:func:`check_recipe`), a TOML file (:func:`recipe_from_dict`)
#: and the commands' options (``cli/recipe_options.py``) are all checked against it
RULES: dict[str, FieldRule] = {
    "preset": FieldRule("choice", words=FEATURE_KINDS),
    "features.kind": FieldRule("choice", words=FEATURE_KINDS),
    "features.weights": FieldRule("text", high=4096, optional=True),
    "features.voxel": FieldRule(
        "number", limits.MIN_LENGTH, limits.MAX_LENGTH, words=("auto", "own")
    ),
    "features.reference_voxel": FieldRule(
        "number", limits.MIN_VOXEL_SIZE, limits.MAX_VOXEL_SIZE, optional=True
    ),
    "matching.max_points": FieldRule("int", 0, limits.MAX_MATCH_POINTS),
    "matching.correspondences": FieldRule("int", 3, limits.MAX_MATCH_POINTS),
    "matching.mutual": FieldRule("bool"),
    "fitting.estimator": FieldRule("choice", words=ESTIMATORS),
    "fitting.inlier_factor": FieldRule("number", 0, limits.MAX_INLIER_FACTOR, low_open=True),
    "fitting.ransac_iterations": FieldRule("int", 1, limits.MAX_RANSAC_ITERATIONS),
    "fitting.ransac_confidence": FieldRule("number", 0, 1, low_open=True),
    "fitting.num_subsets": FieldRule("int", 1, limits.MAX_NUM_SUBSETS),
    "fitting.subset_size": FieldRule("int", 3, limits.MAX_SUBSET_SIZE),
    "refinement.method": FieldRule("choice", words=REFINEMENTS),
    "refinement.restarts": FieldRule("bool"),
    "gate.min_confidence": FieldRule("number", 0, 1),
    "gate.fallback": FieldRule("choice", words=FALLBACKS),
    "seed": FieldRule("int", 0, 2**64 - 1),
}


def check_value(path: str, value: Any) -> None:
    """Raise :class:`RecipeError` unless ``value`` is in the range of field ``path``."""
    rule = RULES[path]
    if not rule.accepts(value):
        raise RecipeError(f"{path} must be {rule.expected()} (got {_describe(value)})")


def _describe(value: Any) -> str:
    """A short phrase for a value of any type (a file's value may be anything)."""
    if isinstance(value, Mapping):
        return "a table"
    if isinstance(value, list | tuple):
        return "an array"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int) and abs(value) >= 10**15:
        return f"an integer of {len(str(abs(value)))} digits"
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def check_recipe(recipe: RegistrationRecipe) -> None:
    """Raise :class:`RecipeError` naming the first field out of its range (:data:`RULES`)."""
    for path in RULES:
        if path == "preset":
            continue
        value: Any = recipe
        for name in path.split("."):
            value = getattr(value, name)
        check_value(path, value)


# ------------------------------------------------------------------ presets

#: the recipe of each feature type (``--features``)
PRESETS: dict[str, RegistrationRecipe] = {
    # learned features: RANSAC on the top 2500 ratio-test matches per direction, then
    # coarse-to-fine point-to-plane ICP on the full clouds that holds sliding directions
    # (benchmarks/estimators.py): randomized Procrustes registered a fifth of the development
    # fragments that RANSAC did with the same features; plain ICP slid along the planes of
    # tum_fr3_cabinet. Below the gate, FPFH gives a second opinion (docs/registering.md).
    "byoc": RegistrationRecipe(
        FeaturesRecipe("byoc"),
        MatchingRecipe(max_points=5000, correspondences=2500),
        FittingRecipe(),
        RefinementRecipe("multiscale"),
        GateRecipe(fallback="fpfh"),
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
            raise RecipeError(f"unknown key {_describe(key)} (known: {', '.join(sorted(known))})")
    values: dict[str, Any] = {}
    for key in ("preset", "seed"):
        if key in data:
            check_value(key, data[key])
            values[key] = data[key]
    for stage, kind_of in _STAGES.items():
        table = data.get(stage, {})
        if not isinstance(table, Mapping):
            raise RecipeError(f"[{stage}] must be a table (got {_describe(table)})")
        names = [f.name for f in fields(kind_of)]
        for name, value in table.items():
            if name not in names:
                raise RecipeError(
                    f"unknown field {stage}.{_describe(name)[1:-1]} (known: {', '.join(names)})"
                )
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
