"""The training loop: model, optimiser, steps, logging, validation, checkpoints, export.

The data comes from :mod:`.loaders`; the run folder (``config.json``, ``metrics.jsonl``,
weights export, resuming a run's configuration) is :mod:`.run_folder`; the names of both
that callers used from here are re-exported.

Resuming from a checkpoint restores the model, the optimiser, every RNG state and the
position in the data order, so a killed run that is resumed ends with bit-identical weights
(on the same device and thread count). Under ``torchrun`` every process trains on its
share of each batch (DDP); only rank 0 writes files.
"""

from __future__ import annotations

import json
import logging
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import torch

from byoc_cli.errors import InputError
from byoc_cli.training.checkpoint import (
    capture_rng_state,
    load_latest_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from byoc_cli.training.config import TrainConfig
from byoc_cli.training.distributed import (
    DistInfo,
    barrier,
    gather_objects,
    init_distributed,
    mean_across,
)
from byoc_cli.training.guard import check_finite, step_guard
from byoc_cli.training.loaders import ResumableLoader, build_datasets
from byoc_cli.training.model import ByocModel, LossTerms
from byoc_cli.training.plot import METRICS_FILE, PLOT_FILE, plot_metrics, read_metrics
from byoc_cli.training.run_folder import (
    CONFIG_FILE,
    WEIGHTS_FILE,
    export_weights,
    has_progress,
    load_initial_weights,
    read_run_config,
    resume_config,
    start_run_folder,
    truncate_metrics,
    write_run_config,
)
from byoc_cli.training.validate import validate

__all__ = [
    "CONFIG_FILE",
    "WEIGHTS_FILE",
    "StepInfo",
    "TrainCallbacks",
    "TrainResult",
    "build_datasets",
    "build_model",
    "build_optimizer",
    "export_weights",
    "read_run_config",
    "resume_config",
    "train",
    "write_run_config",
]

log = logging.getLogger("byoc.train")


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


# ---------------------------------------------------------------------------- the runner
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
    if not resume and (run_dir / CONFIG_FILE).exists() and has_progress(run_dir):
        raise InputError(
            run_dir, "already holds a training run (use --resume to continue it, or another --out)"
        )
    # every process has looked at the folder before rank 0 writes config.json into it
    barrier(info)
    train_set, val_set, data_names = build_datasets(config)

    model = build_model(config, info.rank, _amp_dtype(config, device)).to(device)
    optimizer = build_optimizer(model, config)
    loader = ResumableLoader(train_set, config, info)
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
    if step == 0 and config.init_weights:
        if model.geometric is None:
            raise InputError(
                config.init_weights,
                f"init_weights: --variant {config.variant} has no geometric encoder",
            )
        load_initial_weights(model.geometric, config)
    if info.is_main:
        if not resume:
            start_run_folder(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        write_run_config(run_dir, config, {"world_size": info.world_size, "data": data_names})
        truncate_metrics(run_dir / METRICS_FILE, step)
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
            with step_guard(model, step + 1, config.lr):
                terms: LossTerms = ddp_model(batch)
                optimizer.zero_grad(set_to_none=True)
                terms.total.backward()
                optimizer.step()
                check_finite(terms.total, model.parameters(), step + 1, config.lr)
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
