"""The paper's variants (``byoc``, ``byoc-geo``, ``byoc-rot``, ...) as a task of the loop.

Data: pairs of views of RGB-D frames ``view_spacing`` apart (:mod:`.loaders`), in a
resumable order split over the processes. Step: :class:`~.model.ByocModel`'s losses of the
variant (the paper's section 3). Validation: the test-time pipeline on posed frame pairs
(:mod:`.validate`). Export: the geometric encoder. The loop is :mod:`.loop`.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import torch

from byoc_cli.errors import InputError
from byoc_cli.training.config import TrainConfig
from byoc_cli.training.distributed import DistInfo
from byoc_cli.training.loaders import ResumableLoader, build_datasets
from byoc_cli.training.model import ByocModel, LossTerms
from byoc_cli.training.run_folder import export_weights, load_initial_weights
from byoc_cli.training.validate import validate


def mixed_precision(config: TrainConfig, device: torch.device) -> torch.dtype | None:
    """The mixed-precision dtype of the encoders (bfloat16 on CUDA), or None (float32)."""
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


def deterministic(config: TrainConfig, info: DistInfo) -> bool:
    """Deterministic kernels: ``config.deterministic``, by default on for CPU runs (bit-exact
    resume with several threads), off for CUDA."""
    if config.deterministic is not None:
        return config.deterministic
    return info.device.type == "cpu"


def loss_values(terms: LossTerms) -> dict[str, float]:
    """The logged values of a step's losses."""
    return {
        "loss": float(terms.total.detach()),
        "loss_vis": float(terms.vis.detach()),
        "loss_geo": float(terms.geo.detach()),
        "loss_v2g": float(terms.v2g.detach()),
    }


class PaperTask:
    """A paper variant's model, data, step and validation (a :class:`.task.TrainTask`).

    Raises:
        DatasetError: unusable data folders.
    """

    fused_optimizer = False

    def __init__(self, config: TrainConfig, info: DistInfo) -> None:
        self.config, self.info = config, info
        train_set, self.val_set, self.data_names = build_datasets(config)
        self.model = build_model(config, info.rank, mixed_precision(config, info.device))
        self.model = self.model.to(info.device)
        self.loader = ResumableLoader(train_set, config, info)
        self.generators = {"augment": self.model.aug_generator}
        self.val_samples: list[Any] | None = None
        self._batches = None

    @property
    def validates(self) -> bool:
        return self.val_samples is not None

    def load_initial_weights(self) -> None:
        if not self.config.init_weights:
            return
        if self.model.geometric is None:
            raise InputError(
                self.config.init_weights,
                f"init_weights: --variant {self.config.variant} has no geometric encoder",
            )
        load_initial_weights(self.model.geometric, self.config)

    def data_position(self) -> dict[str, int]:
        return {"epoch": self.loader.epoch, "batch_in_epoch": self.loader.batch_in_epoch}

    def restore_position(self, state: dict[str, Any]) -> None:
        self.loader.epoch = int(state["epoch"])
        self.loader.batch_in_epoch = int(state["batch_in_epoch"])

    def prepare(self, step: int, records: Any, progress: Any = None) -> None:
        del step, records, progress  # the data loaders are ready from the start
        if self.val_samples is None and self.val_set and self.info.is_main:
            self.val_samples = [self.val_set[i] for i in range(len(self.val_set))]

    def next_batch(self) -> Any:
        if self._batches is None:
            self._batches = iter(self.loader)
        return next(self._batches)

    def step(self, module: torch.nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        terms: LossTerms = module(batch)
        return terms.total, loss_values(terms)

    def summarize(self, window: list[dict[str, float]], seconds: float) -> dict[str, float]:
        del seconds
        return {k: sum(w[k] for w in window) / len(window) for k in window[0]}

    def validate(self) -> dict[str, float] | None:
        if self.val_samples is None or self.model.geometric is None:
            return None
        metrics, _ = validate(
            self.model.geometric,
            self.val_samples,
            k=self.config.num_correspondences,
            seed=self.config.seed,
        )
        return metrics

    def checkpoint_due(self, step: int) -> bool:
        del step
        return False

    def export(self, path: Path, steps: int, metrics: dict[str, float]) -> str:
        return export_weights(self.model, self.config, path, self.data_names, steps, metrics)
