"""The run folder: its configuration, metrics log and exported weights.

A run folder holds::

    config.json              the effective configuration (with the code version)
    metrics.jsonl            one JSON object per log line ("train") or validation ("val")
    checkpoints/step-N.pt    the newest checkpoints (atomic; :mod:`.checkpoint`)
    training.png             losses and validation accuracy (:mod:`.plot`)
    weights.safetensors      the final geometric encoder (weights-spec format)
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path, PurePath
from typing import Any

import torch

from byoc_cli.errors import InputError
from byoc_cli.training.config import TrainConfig, config_from_json
from byoc_cli.training.model import ByocModel
from byoc_cli.training.plot import read_metrics

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "weights.safetensors"


def write_run_config(
    run_dir: Path, config: TrainConfig, extra: dict[str, Any] | None = None
) -> None:
    """Write ``config.json`` (the effective configuration and the code version)."""
    from byoc_cli import __version__
    from byoc_cli.io.atomic import atomic_write_text

    doc = {"byoc_cli_version": __version__, "config": config.to_dict(), **(extra or {})}
    atomic_write_text(run_dir / CONFIG_FILE, json.dumps(doc, indent=2, sort_keys=True) + "\n")


def has_progress(run_dir: Path) -> bool:
    """True when a run folder holds a checkpoint or exported weights (work a new run must not
    replace)."""
    from byoc_cli.training.checkpoint import list_checkpoints

    return bool(list_checkpoints(run_dir)) or (run_dir / WEIGHTS_FILE).exists()


def start_run_folder(run_dir: Path) -> None:
    """Make ``run_dir`` ready for a new (not resumed) run.

    A folder whose run never got anywhere (``config.json`` but no checkpoint and no weights:
    it failed or was killed before its first checkpoint) is the tool's own and is started
    over: its configuration, metrics and plot are removed, so the same command (or the fixed
    one) runs again. Cached self-posed pairs stay (they are reused only when made with the
    same settings).

    Raises:
        InputError: ``run_dir`` holds a run with a checkpoint or weights.
    """
    if not (run_dir / CONFIG_FILE).exists():
        return
    if has_progress(run_dir):
        raise InputError(
            run_dir, "already holds a training run (use --resume to continue it, or another --out)"
        )
    from byoc_cli.training.plot import METRICS_FILE, PLOT_FILE

    for name in (METRICS_FILE, PLOT_FILE, CONFIG_FILE):  # config.json last: ours until gone
        (run_dir / name).unlink(missing_ok=True)


class NewRunFolder:
    """What a new run finds at its run folder, so that a run that fails before its first step
    leaves it as it was: no folder when there was none (nor the parents the run made), else
    without the files and folders the run added (``config.json``, ``pseudo_pairs/``, ...).

    Args:
        run_dir: the run folder (``--out``), looked at when this is made.
    """

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = Path(run_dir)
        # the outermost folder this run will create (None: the run folder exists)
        self.created: Path | None = None
        for folder in (self.run_dir, *self.run_dir.parents):
            if folder.exists() or folder.is_symlink():
                break
            self.created = folder
        # the names the folder held (None: not a folder, nothing to undo)
        self.entries: set[str] | None = set()
        if self.created is None:
            is_dir = self.run_dir.is_dir()
            self.entries = {p.name for p in self.run_dir.iterdir()} if is_dir else None

    def undo(self) -> None:
        """Remove what the run created (best effort: a file that cannot go stays)."""
        import shutil

        if self.created is not None:
            shutil.rmtree(self.created, ignore_errors=True)
            return
        if self.entries is None or not self.run_dir.is_dir():
            return
        for path in self.run_dir.iterdir():
            if path.name in self.entries:
                continue
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)


def read_run_config(run_dir: str | Path) -> TrainConfig:
    """The configuration saved in a run folder.

    Raises:
        InputError: not a run folder.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(run_dir, "run folder does not exist")
    return config_from_json(run_dir / CONFIG_FILE)


def truncate_metrics(path: Path, step: int) -> None:
    """Drop the records of ``metrics.jsonl`` written after ``step`` (a killed run may have
    logged past its last checkpoint); rewrite atomically."""
    from byoc_cli.io.atomic import atomic_write_text

    if not path.exists():
        return
    keep = [r for r in read_metrics(path) if int(r.get("step", 0)) <= step]
    atomic_write_text(path, "".join(json.dumps(r, sort_keys=True) + "\n" for r in keep))


class RunRecords:
    """``metrics.jsonl`` of a run: one JSON object a line (keys sorted), appended.

    Records have a ``kind``: ``train`` (a log window's means), ``val`` (a validation) or a
    variant's own (``round`` of ``self-posed``), and the ``step`` they were written at.
    """

    def __init__(self, path: Path) -> None:
        self.path = path

    def write(self, record: dict[str, Any]) -> None:
        """Append one record (flushed)."""
        with open(self.path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(record, sort_keys=True) + "\n")
            fh.flush()

    def read(self) -> list[dict[str, Any]]:
        """Every record so far (none when the file does not exist yet)."""
        return read_metrics(self.path)


def resume_config(run_dir: str | Path, overrides: dict[str, Any]) -> TrainConfig:
    """The saved configuration of a run with the allowed ``overrides`` applied.

    Raises:
        InputError: not a run folder; ValueError: an override of a key fixed by the run.
    """
    from byoc_cli.training.config import RESUMABLE_KEYS, check_keys

    saved = read_run_config(run_dir)
    values = saved.to_dict()
    values["out"] = str(run_dir)
    changes = check_keys({k: v for k, v in overrides.items() if v is not None}, "command line")
    for key, value in changes.items():
        current = values.get(key)
        if isinstance(current, list):
            current = tuple(current)
        if key not in RESUMABLE_KEYS and value != current and key != "out":
            raise ValueError(f"cannot change '{key}' when resuming (the run has {current!r})")
        values[key] = value
    return TrainConfig(**check_keys(values, Path(run_dir) / CONFIG_FILE))


def _geometric_for_export(model: ByocModel, config: TrainConfig) -> torch.nn.Module:
    if model.geometric is not None:
        return model.geometric
    from byoc_cli.models.encoder import build_encoder

    warnings.warn(
        f"variant {config.variant} trains no geometric encoder: the exported weights "
        "hold a randomly initialised one",
        stacklevel=2,
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        return build_encoder(config.arch)


def export_weights(
    model: ByocModel,
    config: TrainConfig,
    path: Path,
    data: list[str],
    steps: int,
    metrics: dict[str, float],
) -> str:
    """Write the geometric encoder as a weights file; returns its SHA-256."""
    return write_encoder(_geometric_for_export(model, config), config, path, data, steps, metrics)


def write_encoder(
    encoder: torch.nn.Module,
    config: TrainConfig,
    path: Path,
    data: list[str],
    steps: int,
    metrics: dict[str, float],
    *,
    recipe: dict[str, Any] | None = None,
    dtype: torch.dtype = torch.float32,
) -> str:
    """Write ``encoder`` (a CPU copy in eval mode) with the run's metadata; returns the SHA-256.

    Non-finite metrics are left out; ``recipe`` is recorded under ``training.recipe``.
    """
    import copy

    from byoc_cli.pipeline.weights import build_metadata, save_weights

    model = copy.deepcopy(encoder).cpu().eval()
    clean = {k: float(v) for k, v in metrics.items() if v is not None and math.isfinite(float(v))}
    meta = build_metadata(
        model,
        voxel_size=config.voxel_size,
        variant=config.variant,
        data=[dataset_name(name) for name in data],
        steps=steps,
        seed=config.seed,
        metrics=clean,
    )
    if recipe is not None:
        meta["training"]["recipe"] = recipe
    if config.val_dir:
        meta["training"]["validation_data"] = [dataset_name(d) for d in config.val_dir]
        meta["training"]["val_spacing"] = config.val_spacing
    if config.init_weights:
        meta["training"]["init_weights"] = _describe_initial_weights(config)
    return save_weights(path, model, meta, dtype=dtype)


def dataset_name(name: str) -> str:
    """A training or validation set as exported metadata names it: a sequence name as given
    (``office/seq1``), but a folder path (absolute, ``~``, ``..``) reduced to its last part,
    so that a weights file names datasets and never the folders of the machine it was
    trained on."""
    path = PurePath(name)
    if path.is_absolute() or name.startswith("~") or ".." in path.parts:
        return path.name
    return name


def _describe_initial_weights(config: TrainConfig) -> dict[str, Any]:
    """``{"file": name, "sha256": ...}`` of the weights a run started from: the file's name
    without its folder; for ``shipped``, also which release shipped them (sha256 None when
    the file is gone by the time the run exports)."""
    import hashlib

    from byoc_cli import __version__

    path = initial_weights_path(config)
    from byoc_cli.io.inputs import read_input

    try:
        digest = hashlib.sha256(read_input(path, "weights")).hexdigest()
    except InputError:
        digest = None
    described: dict[str, Any] = {"file": path.name, "sha256": digest}
    if config.init_weights == SHIPPED:
        described["description"] = f"the weights shipped with byoc-cli {__version__}"
    return described


#: ``init_weights`` value that names the weights shipped with the package
SHIPPED = "shipped"


def initial_weights_path(config: TrainConfig) -> Path | None:
    """The file ``config.init_weights`` names (``shipped``: the package's), or None."""
    if not config.init_weights:
        return None
    if config.init_weights == SHIPPED:
        from byoc_cli.pipeline.default_weights import default_weights_path

        path = default_weights_path()
        if path is None:
            raise InputError(SHIPPED, "init_weights: this installation ships no weights")
        return path
    return Path(config.init_weights)


def load_initial_weights(encoder: torch.nn.Module, config: TrainConfig) -> str | None:
    """Copy the weights of ``config.init_weights`` into ``encoder`` (a fresh run's start).

    Args:
        encoder: the geometric encoder built for ``config.arch``.
        config: the run's settings.

    Returns:
        The SHA-256 of the file read, or None when ``config.init_weights`` is unset.

    Raises:
        WeightsError: the file is missing or not a valid weights file.
        InputError: its architecture is not ``config.arch`` or its voxel size differs.
    """
    path = initial_weights_path(config)
    if path is None:
        return None
    from byoc_cli.pipeline.weights import load_weights

    loaded = load_weights(path)
    arch = loaded.metadata.get("architecture")
    if arch != config.arch or loaded.encoder.config != encoder.config:
        raise InputError(path, f"init_weights: architecture {arch!r} is not --arch {config.arch!r}")
    voxel = float(loaded.metadata.get("voxel_size", config.voxel_size))
    if not math.isclose(voxel, config.voxel_size, rel_tol=1e-6):
        raise InputError(
            path,
            f"init_weights: trained at voxel size {voxel:g} m, this run uses "
            f"{config.voxel_size:g} m (set --voxel-size {voxel:g})",
        )
    encoder.load_state_dict(loaded.encoder.state_dict())
    return loaded.file_sha256
