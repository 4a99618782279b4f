"""What a training variant supplies to the one loop (:mod:`byoc_cli.training.loop`).

A variant is a :class:`TrainTask`: its model, its data (:meth:`~TrainTask.prepare`,
:meth:`~TrainTask.next_batch`), its step (the loss of a batch) and its measurements
(validation, export). The loop owns the rest: the run folder, the optimiser, when to log,
validate and checkpoint, exact resume, processes under ``torchrun``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import torch

from byoc_cli.training.run_folder import RunRecords


class TrainTask(Protocol):
    """What a variant supplies to the loop: its model, data, step and measurements.

    Attributes:
        model: the module whose trainable parameters are optimised and whose state is
            checkpointed (on the training device).
        generators: the variant's named ``torch.Generator`` s (saved with the checkpoints).
        data_names: the training sequences' names (``config.json``, weights metadata).
        fused_optimizer: build Adam fused (one kernel for all tensors).
        validates: whether :meth:`validate` measures anything (on this process).
    """

    model: torch.nn.Module
    generators: dict[str, torch.Generator]
    data_names: list[str]
    fused_optimizer: bool
    validates: bool

    def load_initial_weights(self) -> None:
        """A new run's starting weights (``init_weights``); called at step 0 only."""

    def data_position(self) -> dict[str, int]:
        """Where the data order stands (``epoch``, ``batch_in_epoch``), for a checkpoint."""

    def restore_position(self, state: dict[str, Any]) -> None:
        """Continue the data order from a checkpoint's :meth:`data_position`."""

    def prepare(
        self,
        step: int,
        records: RunRecords,
        progress: Callable[[str, int, int], None] | None = None,
    ) -> None:
        """Make the data of the step after ``step`` completed steps ready (called before the
        first step, then before every step); may write the variant's own records.
        ``progress(stage, done, total)`` hears of long work (:class:`TrainCallbacks`)."""

    def next_batch(self) -> Any:
        """The next training batch."""

    def step(self, module: torch.nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        """The loss of ``batch`` through ``module`` (:attr:`model`, or its DDP wrapper) and
        the step's values to log (``loss`` and the variant's own)."""

    def summarize(self, window: list[dict[str, float]], seconds: float) -> dict[str, float]:
        """A ``train`` record's variant fields: the means of a log window's step values (and
        the variant's rates over its ``seconds``)."""

    def validate(self) -> dict[str, float] | None:
        """The validation metrics of the model as it stands (None: no validation)."""

    def checkpoint_due(self, step: int) -> bool:
        """A checkpoint the variant needs after ``step`` besides ``checkpoint_every``."""

    def export(self, path: Path, steps: int, metrics: dict[str, float]) -> str:
        """Write the trained encoder as a weights file; returns its SHA-256."""
