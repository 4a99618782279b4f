"""Training data: sequences found under the data folders, pair datasets, resumable batches."""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from byoc_cli import limits
from byoc_cli.errors import DatasetError
from byoc_cli.training.config import TrainConfig
from byoc_cli.training.data import (
    PairDataset,
    ResumableSampler,
    collate_pairs,
    sequence_name,
    worker_init,
)
from byoc_cli.training.distributed import DistInfo


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


def _spacing_hint(lengths: list[int], batch_size: int) -> str:
    """What to change when sequences of ``lengths`` frames give too few training pairs: the
    largest ``--view-spacing`` that gives a batch (a sequence of n frames gives n - s pairs
    at spacing s), else ``--batch-size``."""
    for spacing in range(max(lengths, default=1) - 1, 0, -1):
        pairs = sum(max(0, n - spacing) for n in lengths)
        if pairs >= batch_size:
            return (
                f"set --view-spacing {spacing} or less ({pairs} pairs), or a smaller --batch-size"
            )
    pairs = sum(max(0, n - 1) for n in lengths)
    return f"set --batch-size {pairs} or less (at --view-spacing 1), or give longer sequences"


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
        lengths = [len(s.frames) for s in train_seqs]
        raise DatasetError(
            config.rgbd_dir[0],
            f"{len(train)} training pair(s) at view spacing {config.view_spacing} (sequences of "
            f"{', '.join(map(str, lengths))} frames), fewer than the batch size "
            f"{config.batch_size}: {_spacing_hint(lengths, config.batch_size)}",
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


def loader_workers(requested: int) -> int:
    """The data-loading worker processes to start for ``requested`` (``num_workers``):
    at most :func:`byoc_cli.limits.max_workers` (2 per usable core), with a warning when
    clamped, so a typo (``--num-workers 1000000``) cannot fork until the machine runs out
    of memory. The data order does not depend on the number of workers.
    """
    bound = limits.max_workers()
    if requested > bound:
        warnings.warn(
            f"num_workers {requested} is more than {bound} ({limits.WORKERS_PER_CORE} per "
            f"core this process may use); starting {bound} data-loading workers",
            stacklevel=2,
        )
        return bound
    return requested


class ResumableLoader:
    """Endless batches in the sampler's order, resumable at (epoch, batch).

    Each process gets ``batch_size // world_size`` pairs per batch; :attr:`epoch` and
    :attr:`batch_in_epoch` are the position a checkpoint saves and a resume restores.

    Raises:
        ValueError: ``batch_size`` not divisible by the number of processes.
        DatasetError: too few pairs for one batch per process.
    """

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
        workers = loader_workers(config.num_workers)
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
