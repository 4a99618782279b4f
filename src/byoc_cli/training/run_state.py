"""A run's state in its checkpoints, for exact resume.

A checkpoint holds the model, the optimiser, every process's RNG streams (the task's
``generators`` too) and the task's data position
(:meth:`~byoc_cli.training.task.TrainTask.data_position`), so a killed run that is resumed
ends with bit-identical weights (on the same device and thread count). Only rank 0 writes;
every process gives its RNG state. The files are :mod:`byoc_cli.training.checkpoint`'s.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import torch

from byoc_cli.training.checkpoint import (
    capture_rng_state,
    load_latest_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from byoc_cli.training.config import TrainConfig
from byoc_cli.training.distributed import DistInfo, gather_objects
from byoc_cli.training.task import TrainTask

log = logging.getLogger("byoc.train")


def restore_run_state(
    run_dir: Path, task: TrainTask, optimizer: torch.optim.Optimizer, info: DistInfo
) -> int:
    """The step of the newest checkpoint of ``run_dir``, its state restored into the task's
    model, ``optimizer``, the task's data position and this process's RNG streams (0 without
    a checkpoint). A checkpoint written by another number of processes restores all but the
    RNG streams, with a warning."""
    found = load_latest_checkpoint(run_dir)
    if found is None:
        return 0
    state, path = found
    task.model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    task.restore_position(state)
    rng = state["rng"]
    if len(rng) == info.world_size:
        restore_rng_state(rng[info.rank], task.generators)
    else:
        warnings.warn(
            f"{path} was written by {len(rng)} process(es), this run has "
            f"{info.world_size}: RNG streams are re-seeded",
            stacklevel=3,
        )
    log.info("resuming %s at step %d", run_dir, int(state["step"]))
    return int(state["step"])


def save_run_state(
    run_dir: Path,
    step: int,
    task: TrainTask,
    optimizer: torch.optim.Optimizer,
    config: TrainConfig,
    info: DistInfo,
) -> Path | None:
    """Write the checkpoint of ``step`` (keeping ``config.keep_checkpoints``); every process
    gives its RNG streams, rank 0 writes. Returns the checkpoint's path (None on other ranks)."""
    rng_all = gather_objects(info, capture_rng_state(task.generators))
    if not info.is_main:
        return None
    state = {
        "model": task.model.state_dict(),
        "optimizer": optimizer.state_dict(),
        **task.data_position(),
        "rng": rng_all,
        "config": config.to_dict(),
        "world_size": info.world_size,
    }
    return save_checkpoint(run_dir, step, state, keep=config.keep_checkpoints)
