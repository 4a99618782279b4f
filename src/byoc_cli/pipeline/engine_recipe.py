"""A registrar's recipe from its arguments: the preset of its features changed by the
arguments a caller gave (the API's keywords, the CLI's recipe), and its device."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from byoc_cli.pipeline.recipe import RegistrationRecipe


class FromRecipe:
    """The default of an argument that the recipe gives."""

    def __repr__(self) -> str:
        return "<the recipe's>"


#: the default of the registrar's arguments that its recipe gives
FROM_RECIPE: Any = FromRecipe()


def registrar_recipe(
    recipe: RegistrationRecipe | None,
    features: str | None,
    weights: Any,
    voxel_size: Any,
    fallback: str | None,
    fallback_below: float | None,
) -> RegistrationRecipe:
    """The recipe of a :class:`~byoc_cli.pipeline.registrar.Registrar`: ``recipe`` (or the
    preset of ``features``) changed by the arguments that were given.

    Raises:
        ValueError: an unknown feature type, or a fallback that does not go with it.
    """
    from byoc_cli.pipeline.recipe import FEATURE_KINDS, preset

    if features is not None and features not in FEATURE_KINDS:
        raise ValueError(f"features must be one of {sorted(FEATURE_KINDS)}, got {features!r}")
    if recipe is None:
        recipe = preset(features)
    elif features is not None and features != recipe.features.kind:
        recipe = recipe.with_kind(features)
    if fallback == "auto":
        fallback = recipe.gate.fallback if recipe.features.kind == "byoc" else "none"
    if fallback not in (None, "none", "fpfh") or (
        fallback == "fpfh" and recipe.features.kind != "byoc"
    ):
        raise ValueError(f"fallback must be None or 'fpfh' (with byoc features), got {fallback!r}")
    path = weights if isinstance(weights, (str, os.PathLike)) else None
    return recipe.changed(
        features__weights=None if path is None else os.fspath(path),
        features__voxel=None if voxel_size is FROM_RECIPE else voxel_size or "own",
        gate__fallback="none" if fallback is None else fallback,
        gate__min_confidence=fallback_below,
    )


def resolve_device(device: str) -> str:
    """``"cpu"`` or ``"cuda"`` of ``device`` (``"auto"``: cuda when available).

    Raises:
        ValueError: another name.
    """
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda', got {device!r}")
    return device
