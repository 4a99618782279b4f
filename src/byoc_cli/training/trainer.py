"""The training runner: data, model, optimiser, checkpoints, validation, weights export.

A run folder holds::

    config.json              the effective configuration (with the code version)
    metrics.jsonl            one JSON object per log line ("train") or validation ("val")
    checkpoints/step-N.pt    the newest checkpoints (atomic), enough to resume exactly
    training.png             losses and validation accuracy
    weights.safetensors      the final geometric encoder (weights-spec format)

Resuming from a checkpoint restores the model, the optimiser, every RNG state and the
position in the data order, so a killed run that is resumed ends with bit-identical weights
(on the same device and thread count). Under ``torchrun`` every process trains on its
share of each batch (DDP); only rank 0 writes files.
"""

from __future__ import annotations

import json
import logging
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch.utils.data import DataLoader

from byoc_cli.errors import DatasetError, InputError
from byoc_cli.training.checkpoint import (
    capture_rng_state,
    load_latest_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from byoc_cli.training.config import TrainConfig, config_from_json
from byoc_cli.training.data import (
    PairDataset,
    ResumableSampler,
    collate_pairs,
    sequence_name,
    worker_init,
)
from byoc_cli.training.distributed import (
    DistInfo,
    barrier,
    gather_objects,
    init_distributed,
    mean_across,
)
from byoc_cli.training.model import ByocModel, LossTerms
from byoc_cli.training.plot import METRICS_FILE, PLOT_FILE, plot_metrics, read_metrics
from byoc_cli.training.validate import validate

log = logging.getLogger("byoc.train")

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "weights.safetensors"


class StepInfo(NamedTuple):
    """What the progress display gets after every step.

    Attributes:
        step: steps done.
        total: steps in all.
        losses: ``loss``, ``loss_vis``, ``loss_geo``, ``loss_v2g`` of this step.
        steps_per_s: recent throughput.
        eta_s: estimated seconds left.
    """

    step: int
    total: int
    losses: dict[str, float]
    steps_per_s: float
    eta_s: float


@dataclass
class TrainCallbacks:
    """Hooks for progress display (called on rank 0 only). All optional."""

    on_start: Callable[[int, int], None] | None = None
    on_step: Callable[[StepInfo], None] | None = None
    on_log: Callable[[dict[str, Any]], None] | None = None
    on_validation: Callable[[int, dict[str, float]], None] | None = None
    on_checkpoint: Callable[[int, Path], None] | None = None

    def call(self, name: str, *args: Any) -> None:
        hook = getattr(self, name)
        if hook is not None:
            hook(*args)


@dataclass
class TrainResult:
    """Outcome of :func:`train`.

    Attributes:
        run_dir: the run folder.
        weights_path: the exported weights (None on ranks other than 0).
        weights_sha256: SHA-256 of the weights file.
        steps: steps done.
        first_loss, last_loss: mean training loss over the first and last log windows.
        validation: the last validation metrics (empty without ``val_dir``).
        initial_validation: validation before the first step of this run (random init).
    """

    run_dir: Path
    weights_path: Path | None
    weights_sha256: str | None
    steps: int
    first_loss: float | None = None
    last_loss: float | None = None
    validation: dict[str, float] = field(default_factory=dict)
    initial_validation: dict[str, float] = field(default_factory=dict)


# ---------------------------------------------------------------------------- data
def _discover(roots: tuple[str, ...], config: TrainConfig, need_color: bool, label: str) -> list:
    from byoc_cli.io.rgbd import discover_sequences

    intrinsics = Path(config.intrinsics) if config.intrinsics else None
    found = []
    for root in roots:
        path = Path(root)
        if not path.is_dir():
            raise DatasetError(
                path,
                f"{label} folder does not exist"
                if not path.exists()
                else f"{label} path is not a folder",
            )
        seqs = discover_sequences(
            path, intrinsics=intrinsics, depth_scale=config.depth_scale, require_color=need_color
        )
        if not seqs:
            raise DatasetError(path, f"no RGB-D sequence found in this {label} folder")
        found.extend(seqs)
    return found


def build_datasets(config: TrainConfig) -> tuple[PairDataset, PairDataset | None, list[str]]:
    """Training pairs, validation pairs (or None) and the training sequences' names.

    Raises:
        DatasetError: a folder is missing, holds no sequence, or gives no pair.
    """
    if not config.rgbd_dir:
        raise DatasetError("rgbd_dir", "no training folder given (--rgbd-dir)")
    train_seqs = _discover(config.rgbd_dir, config, config.uses_visual, "training")
    train = PairDataset(
        train_seqs,
        config.view_spacing,
        "train",
        config.image_size,
        config.voxel_size,
        use_color=config.uses_visual,
    )
    if len(train) < config.batch_size:
        lengths = ", ".join(str(len(s.frames)) for s in train_seqs)
        raise DatasetError(
            config.rgbd_dir[0],
            f"{len(train)} training pair(s) at view spacing {config.view_spacing} (sequences of "
            f"{lengths} frames), fewer than the batch size {config.batch_size}",
        )
    names = [sequence_name(s, f"{config.rgbd_dir[0]}#{k}") for k, s in enumerate(train_seqs)]
    val = None
    if config.val_dir:
        val_seqs = _discover(config.val_dir, config, False, "validation")
        posed = [s for s in val_seqs if getattr(s, "has_poses", True)]
        if not posed:
            raise DatasetError(config.val_dir[0], "no validation sequence with poses")
        val = PairDataset(
            posed,
            config.val_spacing,
            "val",
            config.image_size,
            config.voxel_size,
            use_color=False,
            with_poses=True,
        ).subset(config.val_max_pairs)
        if len(val) == 0:
            raise DatasetError(
                config.val_dir[0], f"no validation pair at --val-spacing {config.val_spacing}"
            )
    return train, val, names


# ---------------------------------------------------------------------------- run folder
def write_run_config(
    run_dir: Path, config: TrainConfig, extra: dict[str, Any] | None = None
) -> None:
    """Write ``config.json`` (the effective configuration and the code version)."""
    from byoc_cli import __version__
    from byoc_cli.io.atomic import atomic_write_text

    doc = {"byoc_cli_version": __version__, "config": config.to_dict(), **(extra or {})}
    atomic_write_text(run_dir / CONFIG_FILE, json.dumps(doc, indent=2, sort_keys=True) + "\n")


def read_run_config(run_dir: str | Path) -> TrainConfig:
    """The configuration saved in a run folder.

    Raises:
        InputError: not a run folder.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(run_dir, "run folder does not exist")
    return config_from_json(run_dir / CONFIG_FILE)


def _truncate_metrics(path: Path, step: int) -> None:
    """Drop the records written after ``step`` (a killed run may have logged past its last
    checkpoint); rewrite atomically."""
    from byoc_cli.io.atomic import atomic_write_text

    if not path.exists():
        return
    keep = [r for r in read_metrics(path) if int(r.get("step", 0)) <= step]
    atomic_write_text(path, "".join(json.dumps(r, sort_keys=True) + "\n" for r in keep))


# ---------------------------------------------------------------------------- helpers
def _amp_dtype(config: TrainConfig, device: torch.device) -> torch.dtype | None:
    use = config.amp if config.amp is not None else device.type == "cuda"
    if not use or device.type != "cuda":
        return None
    if torch.cuda.is_bf16_supported():
        return torch.bfloat16
    warnings.warn(
        "mixed precision needs bfloat16 support on this GPU; training in float32", stacklevel=2
    )
    return None


def build_model(
    config: TrainConfig, rank: int = 0, amp_dtype: torch.dtype | None = None
) -> ByocModel:
    """A :class:`ByocModel` initialised from ``config.seed`` (global RNG untouched)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = ByocModel(
            variant=config.variant,
            arch=config.arch,
            voxel_size=config.voxel_size,
            num_correspondences=config.num_correspondences,
            rot_max_angle_deg=config.rot_max_angle_deg,
            rot_max_translation=config.rot_max_translation,
            augment_seed=config.seed * 1_000_003 + 17 + rank,
            amp_dtype=amp_dtype,
        )
    return model


def build_optimizer(model: torch.nn.Module, config: TrainConfig) -> torch.optim.Optimizer:
    """Adam (lr, eps, weight decay from the config; constant learning rate)."""
    return torch.optim.Adam(
        [p for p in model.parameters() if p.requires_grad],
        lr=config.lr,
        eps=config.adam_eps,
        weight_decay=config.weight_decay,
    )


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
    import copy

    from byoc_cli.pipeline.weights import build_metadata, save_weights

    encoder = copy.deepcopy(_geometric_for_export(model, config)).cpu().eval()
    clean = {k: float(v) for k, v in metrics.items() if v is not None and math.isfinite(float(v))}
    meta = build_metadata(
        encoder,
        voxel_size=config.voxel_size,
        variant=config.variant,
        data=data,
        steps=steps,
        seed=config.seed,
        metrics=clean,
    )
    return save_weights(path, encoder, meta)


# ---------------------------------------------------------------------------- the runner
class _Loader:
    """Endless batches in the sampler's order, resumable at (epoch, batch)."""

    def __init__(self, dataset: PairDataset, config: TrainConfig, info: DistInfo) -> None:
        if config.batch_size % info.world_size:
            raise ValueError(
                f"batch_size {config.batch_size} is not divisible by the "
                f"{info.world_size} processes"
            )
        self.per_rank = config.batch_size // info.world_size
        self.sampler = ResumableSampler(dataset, info.world_size, info.rank, config.seed)
        self.batches_per_epoch = self.sampler.num_samples // self.per_rank
        if self.batches_per_epoch == 0:
            raise DatasetError(
                config.rgbd_dir[0], "too few training pairs for one batch per process"
            )
        workers = config.num_workers
        self.loader = DataLoader(
            dataset,
            batch_size=self.per_rank,
            sampler=self.sampler,
            drop_last=True,
            num_workers=workers,
            collate_fn=collate_pairs,
            worker_init_fn=worker_init if workers else None,
            persistent_workers=workers > 0,
            prefetch_factor=2 if workers else None,
            generator=torch.Generator().manual_seed(config.seed),  # keeps the global RNG untouched
            pin_memory=False,
        )
        self.epoch = 0
        self.batch_in_epoch = 0

    def __iter__(self):
        while True:
            self.sampler.set_position(self.epoch, self.batch_in_epoch * self.per_rank)
            for batch in self.loader:
                self.batch_in_epoch += 1
                yield batch
                if self.batch_in_epoch >= self.batches_per_epoch:
                    break
            self.epoch += 1
            self.batch_in_epoch = 0


def _loss_dict(terms: LossTerms) -> dict[str, float]:
    return {
        "loss": float(terms.total.detach()),
        "loss_vis": float(terms.vis.detach()),
        "loss_geo": float(terms.geo.detach()),
        "loss_v2g": float(terms.v2g.detach()),
    }


def train(
    config: TrainConfig,
    *,
    resume: bool = False,
    callbacks: TrainCallbacks | None = None,
    info: DistInfo | None = None,
) -> TrainResult:
    """Train (or continue) a run as ``config`` describes.

    Args:
        config: the effective configuration (``config.out`` is the run folder).
        resume: continue from the newest checkpoint of ``config.out``.
        callbacks: progress hooks (rank 0).
        info: process group; default: join torchrun's when present.

    Returns:
        :class:`TrainResult`.

    Raises:
        DatasetError: unusable data folders. InputError: a run folder that already holds a
        run (without ``resume``) or is not one (with ``resume``).
    """
    if config.variant == "self-posed":
        from byoc_cli.training.self_posed import train_self_posed

        return train_self_posed(config, resume, callbacks or TrainCallbacks())
    info = info or init_distributed(config.device)
    deterministic = (
        config.deterministic if config.deterministic is not None else info.device.type == "cpu"
    )
    previous = (
        torch.are_deterministic_algorithms_enabled(),
        torch.is_deterministic_algorithms_warn_only_enabled(),
    )
    torch.use_deterministic_algorithms(deterministic, warn_only=True)
    try:
        return _train(config, resume, callbacks or TrainCallbacks(), info)
    finally:
        torch.use_deterministic_algorithms(previous[0], warn_only=previous[1])


def _train(
    config: TrainConfig, resume: bool, callbacks: TrainCallbacks, info: DistInfo
) -> TrainResult:
    device = info.device
    run_dir = Path(config.out)
    if not resume and (run_dir / CONFIG_FILE).exists():
        raise InputError(
            run_dir, "already holds a training run (use --resume to continue it, or another --out)"
        )
    # every process has looked at the folder before rank 0 writes config.json into it
    barrier(info)
    train_set, val_set, data_names = build_datasets(config)

    model = build_model(config, info.rank, _amp_dtype(config, device)).to(device)
    optimizer = build_optimizer(model, config)
    loader = _Loader(train_set, config, info)
    generators = {"augment": model.aug_generator}

    step = 0
    if resume:
        found = load_latest_checkpoint(run_dir)
        if found is not None:
            state, ckpt_path = found
            model.load_state_dict(state["model"])
            optimizer.load_state_dict(state["optimizer"])
            step = int(state["step"])
            loader.epoch = int(state["epoch"])
            loader.batch_in_epoch = int(state["batch_in_epoch"])
            rng = state["rng"]
            if len(rng) == info.world_size:
                restore_rng_state(rng[info.rank], generators)
            else:
                warnings.warn(
                    f"{ckpt_path} was written by {len(rng)} process(es), this run has "
                    f"{info.world_size}: RNG streams are re-seeded",
                    stacklevel=2,
                )
            log.info("resuming %s at step %d", run_dir, step)
    if info.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        write_run_config(run_dir, config, {"world_size": info.world_size, "data": data_names})
        _truncate_metrics(run_dir / METRICS_FILE, step)
    ddp_model: torch.nn.Module = model
    if info.distributed:
        from torch.nn.parallel import DistributedDataParallel

        ddp_model = DistributedDataParallel(
            model,
            device_ids=[device.index] if device.type == "cuda" else None,
        )

    metrics_path = run_dir / METRICS_FILE
    val_samples = [val_set[i] for i in range(len(val_set))] if (val_set and info.is_main) else None
    result = TrainResult(run_dir, None, None, step)

    def write_record(record: dict[str, Any]) -> None:
        with open(metrics_path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(record, sort_keys=True) + "\n")
            fh.flush()

    def run_validation(at_step: int) -> dict[str, float]:
        if val_samples is None or model.geometric is None:
            return {}
        t0 = time.perf_counter()
        metrics, _ = validate(
            model.geometric, val_samples, k=config.num_correspondences, seed=config.seed
        )
        metrics["val_time_s"] = time.perf_counter() - t0
        write_record({"kind": "val", "step": at_step, **metrics})
        callbacks.call("on_validation", at_step, metrics)
        return metrics

    def checkpoint(at_step: int) -> None:
        rng_all = gather_objects(info, capture_rng_state(generators))
        if not info.is_main:
            return
        state = {
            "model": model.state_dict(),
            "optimizer": optimizer.state_dict(),
            "epoch": loader.epoch,
            "batch_in_epoch": loader.batch_in_epoch,
            "rng": rng_all,
            "config": config.to_dict(),
            "world_size": info.world_size,
        }
        path = save_checkpoint(run_dir, at_step, state, keep=config.keep_checkpoints)
        callbacks.call("on_checkpoint", at_step, path)

    if info.is_main:
        callbacks.call("on_start", step, config.steps)
        if config.val_every and step == 0 and val_samples is not None:
            result.initial_validation = run_validation(0)
            result.validation = result.initial_validation
        elif val_samples is not None:
            previous = [r for r in read_metrics(metrics_path) if r.get("kind") == "val"]
            if previous:
                result.validation = {
                    k: v for k, v in previous[-1].items() if k not in ("kind", "step")
                }
                result.initial_validation = {
                    k: v for k, v in previous[0].items() if k not in ("kind", "step")
                }

    model.train()
    window: list[dict[str, float]] = []
    t_window = time.perf_counter()
    rate = 0.0
    t_rate, rate_steps = time.perf_counter(), 0
    batches = iter(loader)
    try:
        while step < config.steps:
            batch = next(batches)
            terms: LossTerms = ddp_model(batch)
            optimizer.zero_grad(set_to_none=True)
            terms.total.backward()
            optimizer.step()
            step += 1
            losses = _loss_dict(terms)
            window.append(losses)
            rate_steps += 1
            now = time.perf_counter()
            if now - t_rate > 0:
                rate = rate_steps / (now - t_rate)
            if rate_steps >= 20:
                t_rate, rate_steps = now, 0
            if info.is_main:
                eta = (config.steps - step) / rate if rate > 0 else float("nan")
                callbacks.call("on_step", StepInfo(step, config.steps, losses, rate, eta))
            last = step == config.steps
            if (config.log_every and step % config.log_every == 0) or last:
                mean = {k: sum(w[k] for w in window) / len(window) for k in window[0]}
                mean = mean_across(info, mean)
                elapsed = time.perf_counter() - t_window
                record = {
                    "kind": "train",
                    "step": step,
                    **mean,
                    "steps_per_s": len(window) / elapsed if elapsed > 0 else None,
                    "lr": config.lr,
                    "time": time.time(),
                }
                if info.is_main:
                    write_record(record)
                    callbacks.call("on_log", record)
                    if result.first_loss is None:
                        result.first_loss = mean["loss"]
                    result.last_loss = mean["loss"]
                window, t_window = [], time.perf_counter()
            if info.is_main and config.val_every and (step % config.val_every == 0 or last):
                result.validation = run_validation(step)
                plot_metrics(
                    read_metrics(metrics_path),
                    run_dir / PLOT_FILE,
                    f"{config.variant} ({config.arch})",
                )
            if (config.checkpoint_every and step % config.checkpoint_every == 0) or last:
                checkpoint(step)
    except KeyboardInterrupt:
        # lose nothing on Ctrl-C: the state after the last finished step is consistent
        if not info.distributed and step > 0:
            checkpoint(step)
        raise

    result.steps = step
    if info.is_main:
        records = read_metrics(metrics_path)
        train_records = [r for r in records if r.get("kind") == "train"]
        if train_records:
            result.first_loss = train_records[0]["loss"]
            result.last_loss = train_records[-1]["loss"]
        plot_metrics(records, run_dir / PLOT_FILE, f"{config.variant} ({config.arch})")
        export_metrics = {}
        if result.last_loss is not None:
            export_metrics["train_loss"] = result.last_loss
        export_metrics.update(
            {f"val_{k}": v for k, v in result.validation.items() if k != "val_time_s"}
        )
        result.weights_path = run_dir / WEIGHTS_FILE
        result.weights_sha256 = export_weights(
            model, config, result.weights_path, data_names, step, export_metrics
        )
    return result


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
