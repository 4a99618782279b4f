"""The one training loop: run folder, optimiser, steps, records, validation, checkpoints, export.

Every variant runs here. A variant is a :class:`~byoc_cli.training.task.TrainTask`: it
supplies its model, its data, its step (the loss of a batch) and its measurements
(validation, export); the loop owns the rest, the same for all:

* the run folder (``config.json``, ``metrics.jsonl`` records, ``training.png``;
  :mod:`.run_folder`, :mod:`.plot`);
* the optimiser (Adam, :func:`build_optimizer`) and the divergence guard (:mod:`.guard`);
* when to log, validate and checkpoint;
* checkpoints and exact resume: the model, the optimiser, every RNG state (the task's
  ``generators`` too) and the task's data position are saved and restored (:mod:`.run_state`),
  so a killed run that is resumed ends with bit-identical weights (on the same device and
  thread count);
* processes under ``torchrun`` (DDP): every process steps on its share of each batch; only
  rank 0 writes files.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import torch

from byoc_cli.errors import InputError
from byoc_cli.training.config import TrainConfig
from byoc_cli.training.distributed import DistInfo, barrier, mean_across
from byoc_cli.training.guard import check_finite, step_guard
from byoc_cli.training.plot import METRICS_FILE, PLOT_FILE, plot_metrics
from byoc_cli.training.run_folder import (
    CONFIG_FILE,
    WEIGHTS_FILE,
    NewRunFolder,
    RunRecords,
    has_progress,
    start_run_folder,
    truncate_metrics,
    write_run_config,
)
from byoc_cli.training.run_state import restore_run_state, save_run_state
from byoc_cli.training.task import TrainTask

#: the steps the progress display's throughput is measured over
RATE_WINDOW = 20


class StepInfo(NamedTuple):
    """What the progress display gets after every step.

    Attributes:
        step: steps done.
        total: steps in all.
        losses: the step's ``loss*`` values (``loss``, and the paper variants' ``loss_vis``,
            ``loss_geo``, ``loss_v2g``).
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
    """Hooks for progress display (called on rank 0 only). All optional.

    ``on_stage(stage, done, total)`` reports the work a variant does before its steps can
    run (``self-posed``: its pseudo-poses, ``frames``, ``odometry`` and ``pairs``), so that a
    run is never silent for minutes; ``on_start(step, total)`` then opens the steps.
    """

    on_stage: Callable[[str, int, int], None] | None = None
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
    """Outcome of a run.

    Attributes:
        run_dir: the run folder.
        weights_path: the exported weights (None on ranks other than 0).
        weights_sha256: SHA-256 of the weights file.
        steps: steps done.
        first_loss, last_loss: mean training loss over the first and last log windows.
        loss_lines: the ``train`` records (log windows) of the run folder.
        validation: the last validation metrics (empty without ``val_dir``).
        initial_validation: validation before the first step of the run (random init).
    """

    run_dir: Path
    weights_path: Path | None
    weights_sha256: str | None
    steps: int
    first_loss: float | None = None
    last_loss: float | None = None
    loss_lines: int = 0
    validation: dict[str, float] = field(default_factory=dict)
    initial_validation: dict[str, float] = field(default_factory=dict)


def build_optimizer(
    model: torch.nn.Module, config: TrainConfig, *, fused: bool = False
) -> torch.optim.Optimizer:
    """Adam over the trainable parameters (lr, eps, weight decay from the config; constant
    learning rate). ``fused``: one kernel for all tensors (a quarter of the for-loop Adam's
    time on a compact encoder's 6.5 M parameters)."""
    return torch.optim.Adam(
        [p for p in model.parameters() if p.requires_grad],
        lr=config.lr,
        eps=config.adam_eps,
        weight_decay=config.weight_decay,
        **({"fused": True} if fused else {}),
    )


def run_training(
    config: TrainConfig,
    make_task: Callable[[TrainConfig, DistInfo], TrainTask],
    *,
    resume: bool,
    callbacks: TrainCallbacks,
    info: DistInfo,
    deterministic: bool | None,
) -> TrainResult:
    """Train (or continue) a run of the task ``make_task`` builds.

    Args:
        config: the effective configuration (``config.out`` is the run folder).
        make_task: the variant's task from the configuration and the process.
        resume: continue from the newest checkpoint of ``config.out``.
        callbacks: progress hooks (rank 0).
        info: the process group.
        deterministic: ``torch.use_deterministic_algorithms`` during the run (None: leave the
            process's setting).

    Returns:
        :class:`TrainResult`.

    Raises:
        DatasetError: unusable data. InputError: a run folder that already holds a run
        (without ``resume``). TrainingError: the run diverged.
    """
    if deterministic is None:
        return _run_or_undo(config, make_task, resume, callbacks, info)
    previous = (
        torch.are_deterministic_algorithms_enabled(),
        torch.is_deterministic_algorithms_warn_only_enabled(),
    )
    torch.use_deterministic_algorithms(deterministic, warn_only=True)
    try:
        return _run_or_undo(config, make_task, resume, callbacks, info)
    finally:
        torch.use_deterministic_algorithms(previous[0], warn_only=previous[1])


def _run_or_undo(
    config: TrainConfig,
    make_task: Callable[[TrainConfig, DistInfo], TrainTask],
    resume: bool,
    callbacks: TrainCallbacks,
    info: DistInfo,
) -> TrainResult:
    """A :class:`_Run`; a new run that fails (or is interrupted) before its first step leaves
    its run folder as it found it (:class:`NewRunFolder`: none, when there was none)."""
    found = NewRunFolder(Path(config.out)) if not resume and info.is_main else None
    run = None
    try:
        run = _Run(config, make_task, resume, callbacks, info)
        return run.run()
    except BaseException:
        if found is not None and (run is None or run.step == 0):
            found.undo()
        raise


class _Run:
    """One run of the loop (the state :func:`run_training` steps through)."""

    def __init__(
        self,
        config: TrainConfig,
        make_task: Callable[[TrainConfig, DistInfo], TrainTask],
        resume: bool,
        callbacks: TrainCallbacks,
        info: DistInfo,
    ) -> None:
        self.config, self.callbacks, self.info = config, callbacks, info
        self.run_dir = Path(config.out)
        if not resume and (self.run_dir / CONFIG_FILE).exists() and has_progress(self.run_dir):
            raise InputError(
                self.run_dir,
                "already holds a training run (use --resume to continue it, or another --out)",
            )
        # every process has looked at the folder before rank 0 writes config.json into it
        barrier(info)
        self.task = make_task(config, info)
        self.optimizer = build_optimizer(self.task.model, config, fused=self.task.fused_optimizer)
        self.step = (
            restore_run_state(self.run_dir, self.task, self.optimizer, self.info) if resume else 0
        )
        if self.step == 0:
            self.task.load_initial_weights()
        if info.is_main:
            if not resume:
                start_run_folder(self.run_dir)
            self.run_dir.mkdir(parents=True, exist_ok=True)
            extra = {"world_size": info.world_size, "data": self.task.data_names}
            write_run_config(self.run_dir, config, extra)
            truncate_metrics(self.run_dir / METRICS_FILE, self.step)
        self.module: torch.nn.Module = self.task.model
        if info.distributed:
            from torch.nn.parallel import DistributedDataParallel

            device = info.device
            self.module = DistributedDataParallel(
                self.task.model, device_ids=[device.index] if device.type == "cuda" else None
            )
        self.records = RunRecords(self.run_dir / METRICS_FILE)
        self.result = TrainResult(self.run_dir, None, None, self.step)

    # ------------------------------------------------------------------ checkpoints
    def _checkpoint(self) -> None:
        path = save_run_state(
            self.run_dir, self.step, self.task, self.optimizer, self.config, self.info
        )
        if path is not None:
            self.callbacks.call("on_checkpoint", self.step, path)

    # ------------------------------------------------------------------ records
    def _validate(self) -> dict[str, float]:
        """Validate, record and report (rank 0); ``{}`` when the task does not validate."""
        t0 = time.perf_counter()
        metrics = self.task.validate() if self.task.validates else None
        if metrics is None:
            return {}
        metrics["val_time_s"] = time.perf_counter() - t0
        self.records.write({"kind": "val", "step": self.step, **metrics})
        self.callbacks.call("on_validation", self.step, metrics)
        return metrics

    def _plot(self, records: list[dict[str, Any]]) -> None:
        title = f"{self.config.variant} ({self.config.arch})"
        plot_metrics(records, self.run_dir / PLOT_FILE, title)

    def _start_validation(self) -> None:
        """Validation before the first step; on resume, the figures recorded so far."""
        result = self.result
        if self.config.val_every and self.step == 0 and self.task.validates:
            result.initial_validation = self._validate()
            result.validation = result.initial_validation
        elif self.task.validates:
            previous = [r for r in self.records.read() if r.get("kind") == "val"]
            if previous:
                skip = ("kind", "step")
                result.validation = {k: v for k, v in previous[-1].items() if k not in skip}
                result.initial_validation = {k: v for k, v in previous[0].items() if k not in skip}

    # ------------------------------------------------------------------ the loop
    def run(self) -> TrainResult:
        config, info, task = self.config, self.info, self.task
        task.prepare(self.step, self.records, self._stage)
        if info.is_main:
            self.callbacks.call("on_start", self.step, config.steps)
            self._start_validation()
        task.model.train()
        try:
            self._steps()
        except KeyboardInterrupt:
            # lose nothing on Ctrl-C: the state after the last finished step is consistent
            if not info.distributed and self.step > 0:
                self._checkpoint()
            raise
        self.result.steps = self.step
        if info.is_main:
            self._export()
        self._release()
        return self.result

    def _stage(self, stage: str, done: int, total: int) -> None:
        """A task's progress before its steps (rank 0 reports it)."""
        if self.info.is_main:
            self.callbacks.call("on_stage", stage, done, total)

    def _release(self) -> None:
        """End a distributed run together: every process waits for rank 0's export and
        drops its DDP wrapper before the process group is destroyed (a process that tears
        the group down while its peer still uses it aborts in gloo's threads)."""
        if self.info.distributed:
            barrier(self.info)
            self.module = self.task.model

    def _steps(self) -> None:
        config, info, task = self.config, self.info, self.task
        window: list[dict[str, float]] = []
        t_window = time.perf_counter()
        rate = 0.0
        t_rate, rate_steps = time.perf_counter(), 0
        while self.step < config.steps:
            task.prepare(self.step, self.records, self._stage)
            batch = task.next_batch()
            with step_guard(task.model, self.step + 1, config.lr):
                loss, values = task.step(self.module, batch)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                self.optimizer.step()
                check_finite(loss, task.model.parameters(), self.step + 1, config.lr)
            self.step += 1
            step = self.step
            window.append(values)
            rate_steps += 1
            now = time.perf_counter()
            if now - t_rate > 0:
                rate = rate_steps / (now - t_rate)
            if rate_steps >= RATE_WINDOW:
                t_rate, rate_steps = now, 0
            if info.is_main:
                eta = (config.steps - step) / rate if rate > 0 else float("nan")
                losses = {k: v for k, v in values.items() if k.startswith("loss")}
                self.callbacks.call("on_step", StepInfo(step, config.steps, losses, rate, eta))
            last = step == config.steps
            if (config.log_every and step % config.log_every == 0) or last:
                self._log(window, time.perf_counter() - t_window)
                window, t_window = [], time.perf_counter()
            if info.is_main and config.val_every and (step % config.val_every == 0 or last):
                self.result.validation = self._validate()
                self._plot(self.records.read())
            every = config.checkpoint_every and step % config.checkpoint_every == 0
            if every or last or task.checkpoint_due(step):
                self._checkpoint()

    def _log(self, window: list[dict[str, float]], seconds: float) -> None:
        """The ``train`` record of a log window (written by rank 0)."""
        fields = mean_across(self.info, self.task.summarize(window, seconds))
        record = {
            "kind": "train",
            "step": self.step,
            **fields,
            "steps_per_s": len(window) / seconds if seconds > 0 else None,
            "lr": self.config.lr,
            "time": time.time(),
        }
        if self.info.is_main:
            self.records.write(record)
            self.callbacks.call("on_log", record)

    def _export(self) -> None:
        """Losses from the records, the plot, the weights file (rank 0)."""
        result = self.result
        records = self.records.read()
        train_records = [r for r in records if r.get("kind") == "train"]
        if train_records:
            result.first_loss = train_records[0]["loss"]
            result.last_loss = train_records[-1]["loss"]
        result.loss_lines = len(train_records)
        self._plot(records)
        metrics = {}
        if result.last_loss is not None:
            metrics["train_loss"] = result.last_loss
        metrics.update({f"val_{k}": v for k, v in result.validation.items() if k != "val_time_s"})
        result.weights_path = self.run_dir / WEIGHTS_FILE
        result.weights_sha256 = self.task.export(result.weights_path, self.step, metrics)
