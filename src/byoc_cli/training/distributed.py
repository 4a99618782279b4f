"""Process-group helpers for ``torchrun`` (DDP): NCCL on GPUs, gloo on CPUs.

Without the ``torchrun`` environment (``WORLD_SIZE`` unset or 1) everything degrades to
a single process and no process group is created.
"""

from __future__ import annotations

import gc
import os
from datetime import timedelta
from typing import Any, NamedTuple

import torch
import torch.distributed as dist


class DistInfo(NamedTuple):
    """Where this process stands.

    Attributes:
        rank, world_size, local_rank: from the torchrun environment (0, 1, 0 alone).
        backend: ``"nccl"``, ``"gloo"`` or None (single process).
        device: this process's device.
    """

    rank: int
    world_size: int
    local_rank: int
    backend: str | None
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.backend is not None


def resolve_device(device: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def init_distributed(device: str = "auto", timeout_s: float = 1800.0) -> DistInfo:
    """Join the torchrun process group when there is one.

    Args:
        device: ``auto``, ``cpu`` or ``cuda``; CUDA processes use ``cuda:LOCAL_RANK`` and
            NCCL, CPU processes gloo.
        timeout_s: collective timeout.

    Returns:
        :class:`DistInfo`.
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    base = resolve_device(device)
    if base.type == "cuda":
        base = torch.device("cuda", local_rank if world_size > 1 else (base.index or 0))
        torch.cuda.set_device(base)
    if world_size <= 1:
        return DistInfo(0, 1, 0, None, base)
    backend = "nccl" if base.type == "cuda" else "gloo"
    if not dist.is_initialized():
        dist.init_process_group(backend=backend, timeout=timedelta(seconds=timeout_s))
    return DistInfo(dist.get_rank(), dist.get_world_size(), local_rank, backend, base)


def shutdown(info: DistInfo) -> None:
    """Leave the process group (no-op alone).

    Objects that still hold the group (a DDP wrapper in a reference cycle) are collected
    first, so that gloo's threads are joined here and not at interpreter exit.
    """
    if info.distributed and dist.is_initialized():
        gc.collect()
        dist.destroy_process_group()


def barrier(info: DistInfo) -> None:
    """Wait for every process (no-op alone)."""
    if info.distributed:
        dist.barrier()


def gather_objects(info: DistInfo, obj: Any) -> list[Any]:
    """Every process's ``obj``, in rank order (``[obj]`` alone)."""
    if not info.distributed:
        return [obj]
    out: list[Any] = [None] * info.world_size
    dist.all_gather_object(out, obj)
    return out


def broadcast_object(info: DistInfo, obj: Any) -> Any:
    """Rank 0's ``obj`` on every process."""
    if not info.distributed:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def mean_across(info: DistInfo, values: dict[str, float]) -> dict[str, float]:
    """Average scalar logs over processes (for rank 0's log lines)."""
    if not info.distributed or not values:
        return values
    keys = sorted(values)
    t = torch.tensor(
        [float(values[k]) for k in keys],
        dtype=torch.float64,
        device=info.device if info.backend == "nccl" else "cpu",
    )
    dist.all_reduce(t)
    t /= info.world_size
    return dict(zip(keys, t.tolist(), strict=True))
