"""``train``: a run of the variant a configuration names, through the one loop.

The loop is :mod:`.loop`; the variants supply their data and step: the paper's
(:class:`.paper.PaperTask`) and ``self-posed`` (:class:`.self_posed.SelfPosedTask`). The
names callers used from here (the loop's types, the run folder's helpers) are re-exported.
"""

from __future__ import annotations

import torch

from byoc_cli.training.config import TrainConfig
from byoc_cli.training.distributed import DistInfo, init_distributed
from byoc_cli.training.loop import (
    StepInfo,
    TrainCallbacks,
    TrainResult,
    build_optimizer,
    run_training,
)
from byoc_cli.training.paper import PaperTask, build_model, deterministic
from byoc_cli.training.run_folder import (
    CONFIG_FILE,
    WEIGHTS_FILE,
    read_run_config,
    resume_config,
    write_run_config,
)
from byoc_cli.training.self_posed import SelfPosedTask

__all__ = [
    "CONFIG_FILE",
    "WEIGHTS_FILE",
    "StepInfo",
    "TrainCallbacks",
    "TrainResult",
    "build_model",
    "build_optimizer",
    "read_run_config",
    "resume_config",
    "train",
    "write_run_config",
]

#: ``self-posed`` runs as one process on the CPU (torchrun's group is not joined)
_ONE_CPU_PROCESS = DistInfo(0, 1, 0, None, torch.device("cpu"))


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
        :class:`~byoc_cli.training.loop.TrainResult`.

    Raises:
        DatasetError: unusable data folders. InputError: a run folder that already holds a
        run (without ``resume``) or is not one (with ``resume``). TrainingError: the run
        diverged.
    """
    callbacks = callbacks or TrainCallbacks()
    if config.variant == "self-posed":
        return run_training(
            config,
            SelfPosedTask,
            resume=resume,
            callbacks=callbacks,
            info=_ONE_CPU_PROCESS,
            deterministic=None,
        )
    info = info or init_distributed(config.device)
    return run_training(
        config,
        PaperTask,
        resume=resume,
        callbacks=callbacks,
        info=info,
        deterministic=deterministic(config, info),
    )
