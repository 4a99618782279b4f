"""What every field of a registration recipe accepts, said once: its type and range.

:data:`RULES` holds one :class:`FieldRule` per field of a
:class:`~byoc_cli.pipeline.recipe.RegistrationRecipe` (``"stage.field"``, ``"seed"``) and for a
recipe file's ``preset``. A recipe in code (:func:`check_recipe`), a TOML file
(:func:`byoc_cli.pipeline.recipe.recipe_from_dict`) and the commands' options
(``cli/recipe_options.py``) are all checked against it; a value out of its range is a
:class:`RecipeError` that names the field.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from byoc_cli import limits

if TYPE_CHECKING:
    from byoc_cli.pipeline.recipe import RegistrationRecipe

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
    "matching.turns": FieldRule("bool", words=("auto",)),
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
    "gate.retries": FieldRule("int", 0, limits.MAX_RETRIES),
    "gate.recheck": FieldRule("bool"),
    "gate.visibility": FieldRule("bool"),
    "seed": FieldRule("int", 0, 2**64 - 1),
}


def check_value(path: str, value: Any) -> None:
    """Raise :class:`RecipeError` unless ``value`` is in the range of field ``path``."""
    rule = RULES[path]
    if not rule.accepts(value):
        raise RecipeError(f"{path} must be {rule.expected()} (got {describe_value(value)})")


def describe_value(value: Any) -> str:
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
