"""Training configuration: defaults < TOML config file < explicit command-line flags.

The defaults are the paper's, except for the variant ``byoc train`` runs when none is named,
:data:`DEFAULT_VARIANT` (``self-posed``, the one that learns on a CPU), whose defaults are
the recipe of the shipped weights (:data:`SHIPPED_RECIPE`: a fine-tune of them).

The key names of :class:`TrainConfig` are public API (TOML files, ``config.json`` in a run
folder); an unknown key is refused with the closest known spelling.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from byoc_cli import limits
from byoc_cli.errors import InputError
from byoc_cli.io.inputs import read_input

VARIANTS = ("byoc", "byoc-geo", "byoc-vis", "byoc-rot", "self-posed")
#: variants with a visual branch (need colour images)
VISUAL_VARIANTS = ("byoc", "byoc-vis", "byoc-rot")
#: variants with a geometric branch
GEOMETRIC_VARIANTS = ("byoc", "byoc-geo", "byoc-rot", "self-posed")
#: metric losses of the ``self-posed`` variant
METRIC_LOSSES = ("infonce", "hardest-contrastive")
#: the variant of a run that names none: the paper's variants do not learn on a CPU
#: (docs/experiments/2026-11-26-self-posed-campaign.md); this one made the shipped weights
DEFAULT_VARIANT = "self-posed"
#: the defaults of ``self-posed`` where they differ from the paper's: the recipe of the shipped
#: weights (run ``ft1``: their metadata's ``training.recipe``, steps and ``init_weights``), a
#: fine-tune of the shipped weights on 0.6 m crops
SHIPPED_RECIPE = {
    "steps": 4900,
    "batch_size": 2,
    "lr": 1e-4,
    "crop_radius": 0.6,
    "init_weights": "shipped",
}
#: architecture and voxel size of the shipped weights: only such a run can start from them
SHIPPED_ARCH = "compact"
SHIPPED_VOXEL_SIZE = 0.025
#: ``init_weights`` value for a random start (when the variant's default is the shipped weights)
NO_INIT = "none"

#: keys that may change when a run is resumed; every other key is fixed by the run
RESUMABLE_KEYS = frozenset(
    {
        "steps",
        "val_every",
        "checkpoint_every",
        "num_workers",
        "log_every",
        "device",
        "amp",
        "keep_checkpoints",
        "val_dir",
        "deterministic",
        "val_spacing",
        "val_max_pairs",
    }
)


@dataclass(frozen=True)
class TrainConfig:
    """Every setting of a training run (the paper's sections 3 and 4, Training Details;
    docs/training.md).

    Attributes:
        rgbd_dir: training video folders (each may hold several sequences).
        val_dir: validation video folders with poses (empty: no validation).
        out: the run folder.
        variant: ``byoc``, ``byoc-geo``, ``byoc-vis`` or ``byoc-rot``.
        arch: geometric encoder architecture name (``compact`` or ``minkunet34c``).
        steps: optimiser steps in all.
        batch_size: pairs per step, over all processes.
        lr, adam_eps, weight_decay: Adam (constant learning rate).
        seed: seeds initialisation, data order and augmentation.
        view_spacing: frames between the two views of a training pair.
        val_spacing: frames between consecutive validation frames.
        val_every, checkpoint_every, log_every: intervals in steps (0 = never, except the end).
        val_max_pairs: at most this many validation pairs, evenly spread (0 = all).
        num_workers: data-loading worker processes per training process.
        device: ``auto``, ``cpu`` or ``cuda``.
        amp: mixed precision for the encoders on CUDA (None = on where CUDA is used).
        deterministic: deterministic kernels (``torch.use_deterministic_algorithms``), needed
            for bit-exact resume with several CPU threads; None = on for CPU, off for CUDA.
        voxel_size: geometric voxel size in metres.
        num_correspondences: top-k ratio-test matches per direction.
        image_size: side of the square crop fed to the encoders.
        intrinsics: intrinsics file for folders that ship none (None = discover).
        depth_scale: depth units per metre (None = the layout's convention).
        rot_max_angle_deg, rot_max_translation: byoc-rot augmentation ranges.
        keep_checkpoints: how many most recent checkpoints to keep.
        num_positives: ``self-posed``: correspondences per pair in the metric loss.
        loss: ``self-posed``: the metric loss, ``infonce`` (symmetric InfoNCE) or
            ``hardest-contrastive`` (FCGF's, with ``pos_margin`` and ``neg_margin``).
        temperature: ``self-posed``: InfoNCE temperature.
        pos_margin, neg_margin: ``self-posed``: hardest-contrastive margins (feature distance).
        aug_rotation_deg: ``self-posed``: each view is rotated by an angle up to this.
        aug_scale: ``self-posed``: shared scale jitter ``1 +- aug_scale``.
        aug_min_keep: ``self-posed``: each view keeps a random share >= this of its points.
        pair_gaps: ``self-posed``: frame distances of the self-posed pairs.
        pair_min_fitness: ``self-posed``: smallest ICP fitness (share of the source frame's
            points matched, an overlap) of a kept wide pair; lower keeps pairs of lower overlap.
        crop_radius: ``self-posed``: both views cut to a ball of this radius (m); 0 = off.
        aug_hole_prob, aug_hole_min_keep: ``self-posed``: with this probability a view loses
            a random share of its occupied voxels, keeping at least ``aug_hole_min_keep`` of
            them (density augmentation; 0 = off).
        round_steps: ``self-posed``: steps per round (0: one round). Each later round poses the
            sequences again, with the encoder as trained so far as the global registration,
            and trains on those pairs.
        round_gaps: ``self-posed``: frame distances added to ``pair_gaps`` from round 2 on.
        pairs_from: ``self-posed``: an earlier run folder whose self-posed pairs are reused
            for the same sequences made with the same settings (None: estimate them).
        init_weights: a weights file (or ``shipped``: the weights that ship with the package)
            the geometric encoder starts from instead of ``seed``'s random initialisation
            (fine-tuning); same architecture. Only a new run reads it: ``resume`` continues
            from the checkpoint.
    """

    rgbd_dir: tuple[str, ...] = ()
    val_dir: tuple[str, ...] = ()
    out: str = "runs/byoc"
    variant: str = "byoc"
    arch: str = "compact"
    steps: int = 200_000
    batch_size: int = 8
    lr: float = 1e-4
    adam_eps: float = 1e-4
    weight_decay: float = 1e-6
    seed: int = 8
    view_spacing: int = 20
    val_spacing: int = 20
    val_every: int = 5000
    checkpoint_every: int = 1000
    log_every: int = 10
    val_max_pairs: int = 0
    num_workers: int = 2
    device: str = "auto"
    amp: bool | None = None
    deterministic: bool | None = None
    voxel_size: float = 0.025
    num_correspondences: int = 200
    image_size: int = 128
    intrinsics: str | None = None
    depth_scale: float | None = None
    rot_max_angle_deg: float = 80.0
    rot_max_translation: float = 0.5
    keep_checkpoints: int = 2
    num_positives: int = 1024
    loss: str = "infonce"
    temperature: float = 0.1
    pos_margin: float = 0.1
    neg_margin: float = 1.4
    aug_rotation_deg: float = 60.0
    aug_scale: float = 0.05
    aug_min_keep: float = 0.7
    pair_gaps: tuple[int, ...] = (5, 10, 15, 20, 30, 40, 50, 60)
    pair_min_fitness: float = 0.3
    crop_radius: float = 0.0
    aug_hole_prob: float = 0.0
    aug_hole_min_keep: float = 0.25
    round_steps: int = 0
    round_gaps: tuple[int, ...] = (80, 100, 120)
    pairs_from: str | None = None
    init_weights: str | None = None

    def __post_init__(self) -> None:
        for name in ("pair_gaps", "round_gaps"):
            object.__setattr__(self, name, tuple(int(g) for g in getattr(self, name)))
        problems = []
        if self.variant not in VARIANTS:
            problems.append(f"variant must be one of {', '.join(VARIANTS)}, got {self.variant!r}")
        for name in (
            "steps",
            "batch_size",
            "view_spacing",
            "val_spacing",
            "num_correspondences",
            "image_size",
            "keep_checkpoints",
            "num_positives",
        ):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in (
            "val_every",
            "checkpoint_every",
            "log_every",
            "val_max_pairs",
            "num_workers",
            "seed",
            "round_steps",
        ):
            if getattr(self, name) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(self, name)}")
        if not self.pair_gaps or min(self.pair_gaps) < 1:
            problems.append(f"pair_gaps must be positive frame distances, got {self.pair_gaps}")
        if self.round_gaps and min(self.round_gaps) < 1:
            problems.append(f"round_gaps must be positive frame distances, got {self.round_gaps}")
        if not 0 < self.pair_min_fitness <= 1:
            problems.append(f"pair_min_fitness must be in (0, 1], got {self.pair_min_fitness}")
        if not self.crop_radius >= 0:
            problems.append(f"crop_radius must be >= 0, got {self.crop_radius}")
        if not 0 <= self.aug_hole_prob <= 1 or not 0 < self.aug_hole_min_keep <= 1:
            problems.append("aug_hole_prob must be in [0, 1] and aug_hole_min_keep in (0, 1]")
        if not 0 < self.aug_min_keep <= 1 or not 0 <= self.aug_scale < 1:
            problems.append("aug_min_keep must be in (0, 1] and aug_scale in [0, 1)")
        for name in ("lr", "adam_eps", "voxel_size", "temperature"):
            if not getattr(self, name) > 0:
                problems.append(f"{name} must be > 0, got {getattr(self, name)}")
        problems += self._range_problems()
        if self.loss not in METRIC_LOSSES:
            problems.append(f"loss must be one of {', '.join(METRIC_LOSSES)}, got {self.loss!r}")
        if not 0 <= self.pos_margin < self.neg_margin <= 2:
            problems.append(
                "pos_margin and neg_margin must satisfy 0 <= pos_margin < neg_margin <= 2, got "
                f"{self.pos_margin} and {self.neg_margin}"
            )
        if self.weight_decay < 0:
            problems.append(f"weight_decay must be >= 0, got {self.weight_decay}")
        if self.device not in ("auto", "cpu", "cuda"):
            problems.append(f"device must be auto, cpu or cuda, got {self.device!r}")
        if problems:
            raise ValueError("; ".join(problems))

    def _range_problems(self) -> list[str]:
        """The settings outside the ranges of :mod:`byoc_cli.limits` (the flags' ranges)."""
        ranges = {
            "lr": (0.0, limits.MAX_LR),
            "voxel_size": (limits.MIN_VOXEL_SIZE, limits.MAX_VOXEL_SIZE),
            "depth_scale": (limits.MIN_DEPTH_SCALE, limits.MAX_DEPTH_SCALE),
        }
        problems = []
        for name, (low, high) in ranges.items():
            value = getattr(self, name)
            if value is None or (name != "depth_scale" and not value > 0):  # said above
                continue
            if not low <= value <= high:
                problems.append(f"{name} must be in [{low:g}, {high:g}], got {value:g}")
        return problems

    @property
    def uses_visual(self) -> bool:
        return self.variant in VISUAL_VARIANTS

    @property
    def uses_geometric(self) -> bool:
        return self.variant in GEOMETRIC_VARIANTS

    def round_of(self, step: int) -> int:
        """``self-posed``: the round (from 1) that the step after ``step`` completed steps
        belongs to (always 1 without ``round_steps``)."""
        return 1 + step // self.round_steps if self.round_steps else 1

    def to_dict(self) -> dict[str, Any]:
        """The public keys and their values (JSON-ready)."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            out[f.name] = list(value) if isinstance(value, tuple) else value
        return out


def config_keys() -> list[str]:
    """The public configuration keys, in declaration order."""
    return [f.name for f in dataclasses.fields(TrainConfig)]


_TUPLE_KEYS = ("rgbd_dir", "val_dir")


def _coerce(key: str, value: Any, source: object) -> Any:
    if key in _TUPLE_KEYS:
        if isinstance(value, str):
            return (value,)
        if isinstance(value, list | tuple) and all(isinstance(v, str) for v in value):
            return tuple(value)
        raise InputError(source, f"'{key}' must be a path or a list of paths")
    ref = TrainConfig.__dataclass_fields__[key].default
    if key in ("pair_gaps", "round_gaps"):
        if (
            isinstance(value, list | tuple)
            and (value or key == "round_gaps")
            and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
        ):
            return tuple(value)
        raise InputError(source, f"'{key}' must be a list of integers, got {value!r}")
    if isinstance(ref, bool) or key in ("amp", "deterministic"):
        if value is None or isinstance(value, bool):
            return value
        raise InputError(source, f"'{key}' must be true or false")
    if isinstance(ref, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(source, f"'{key}' must be an integer, got {value!r}")
        return value
    if isinstance(ref, float) or key == "depth_scale":
        if value is None and key == "depth_scale":
            return None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InputError(source, f"'{key}' must be a number, got {value!r}")
        if not math.isfinite(value):
            raise InputError(source, f"'{key}' must be a finite number, got {value!r}")
        return float(value)
    if value is not None and not isinstance(value, str):
        raise InputError(source, f"'{key}' must be a string, got {value!r}")
    return value


def check_keys(values: dict[str, Any], source: object) -> dict[str, Any]:
    """Validate key names and value types of a mapping of settings.

    Raises:
        InputError: an unknown key (with the closest known spelling) or a wrong type.
    """
    known = config_keys()
    out = {}
    for key, value in values.items():
        if key not in known:
            close = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise InputError(source, f"unknown config key '{key}'{hint}")
        out[key] = _coerce(key, value, source)
    return out


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a TOML config (keys at the top level or under ``[train]``).

    Relative paths in ``rgbd_dir``, ``val_dir``, ``out`` and ``intrinsics`` stay relative
    to the working directory (like the flags).

    Raises:
        InputError: missing, unreadable or invalid file, unknown key, wrong type.
    """
    path = Path(path)
    try:
        raw = tomllib.loads(read_input(path, "config").decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise InputError(path, f"cannot read ({exc})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, f"not valid TOML ({exc})") from exc
    except RecursionError as exc:
        raise InputError(path, "not valid TOML (nested too deeply)") from exc
    if set(raw) == {"train"} and isinstance(raw["train"], dict):
        raw = raw["train"]
    return check_keys(raw, path)


def resolve_config(
    file_values: dict[str, Any] | None = None, flag_values: dict[str, Any] | None = None
) -> TrainConfig:
    """Merge settings: dataclass defaults < config file < explicit flags.

    Args:
        file_values: from :func:`load_config_file` (or None).
        flag_values: flags the user gave explicitly; ``None`` values are ignored.

    Returns:
        The effective :class:`TrainConfig`: :data:`DEFAULT_VARIANT` when no variant is
        given, with the variant's defaults (:func:`variant_defaults`) under the file and the
        flags; ``init_weights = "none"`` is a random start.

    Raises:
        InputError: unknown key; ValueError: an out-of-range value.
    """
    merged: dict[str, Any] = {}
    merged.update(file_values or {})
    merged.update(
        check_keys({k: v for k, v in (flag_values or {}).items() if v is not None}, "command line")
    )
    variant = merged.get("variant", DEFAULT_VARIANT)
    merged = {"variant": variant, **variant_defaults(variant, merged), **merged}
    if merged.get("init_weights") == NO_INIT:
        merged["init_weights"] = None
    return TrainConfig(**merged)


def variant_defaults(variant: str, values: dict[str, Any]) -> dict[str, Any]:
    """The defaults of ``variant`` that differ from the paper's (:data:`SHIPPED_RECIPE` for
    ``self-posed``; the shipped start only for their architecture and voxel size, which
    ``values``, the settings given, may change)."""
    if variant != "self-posed":
        return {}
    defaults = dict(SHIPPED_RECIPE)
    arch = values.get("arch", TrainConfig.arch)
    voxel_size = values.get("voxel_size", TrainConfig.voxel_size)
    if arch != SHIPPED_ARCH or not math.isclose(voxel_size, SHIPPED_VOXEL_SIZE):
        del defaults["init_weights"]
    return defaults


def config_from_json(path: str | Path) -> TrainConfig:
    """Read the ``config.json`` of a run folder back.

    Raises:
        InputError: missing or malformed file.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file (not a run folder?)")
    try:
        data = json.loads(read_input(path, "config"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(path, f"cannot read run config ({type(exc).__name__})") from exc
    if not isinstance(data, dict):
        raise InputError(path, "cannot read run config (not a JSON object)")
    values = data.get("config", data)
    return TrainConfig(**check_keys(values, path))
