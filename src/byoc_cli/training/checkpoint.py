"""Training checkpoints: everything needed to continue a run exactly, written atomically.

A checkpoint is a ``torch.save`` dict of tensors and plain Python values only (read back
with ``weights_only=True``): model and optimiser state, the step, the data position
(epoch and samples consumed in it), and every RNG state (torch CPU and CUDA, Python,
NumPy, and the named ``torch.Generator`` s of the run).
"""

from __future__ import annotations

import io
import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from byoc_cli.errors import InputError
from byoc_cli.io.inputs import open_input

CHECKPOINT_FORMAT = "byoc-train-checkpoint"
CHECKPOINT_VERSION = 1
CHECKPOINT_DIR = "checkpoints"
_NAME = re.compile(r"^step-(\d+)\.pt$")


def checkpoint_path(run_dir: str | Path, step: int) -> Path:
    """``RUN/checkpoints/step-00000100.pt``."""
    return Path(run_dir) / CHECKPOINT_DIR / f"step-{step:08d}.pt"


def list_checkpoints(run_dir: str | Path) -> list[tuple[int, Path]]:
    """``(step, path)`` of the checkpoints of a run, oldest first."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    if not folder.is_dir():
        return []
    found = []
    for path in folder.iterdir():
        match = _NAME.match(path.name)
        if match:
            found.append((int(match.group(1)), path))
    return sorted(found)


def capture_rng_state(generators: dict[str, torch.Generator] | None = None) -> dict[str, Any]:
    """Every RNG state of this process: torch CPU/CUDA, Python, NumPy and ``generators``."""
    # the global NumPy state is saved only so that third-party code that draws from it resumes
    # exactly; our own code never draws from it
    np_state = np.random.get_state()  # noqa: NPY002
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "python": random.getstate(),
        "numpy": [
            np_state[0],
            torch.from_numpy(np.asarray(np_state[1]).astype(np.int64)),
            int(np_state[2]),
            int(np_state[3]),
            float(np_state[4]),
        ],
        "generators": {name: g.get_state() for name, g in (generators or {}).items()},
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(
    state: dict[str, Any], generators: dict[str, torch.Generator] | None = None
) -> None:
    """Inverse of :func:`capture_rng_state` (CUDA states only where CUDA is present)."""
    torch.set_rng_state(state["torch"])
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state(  # noqa: NPY002
        (name, keys.numpy().astype(np.uint32), pos, has_gauss, cached)
    )
    if "cuda" in state and torch.cuda.is_available():
        cuda_states = state["cuda"]
        if len(cuda_states) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(cuda_states)
    for name, g in (generators or {}).items():
        if name in state["generators"]:
            g.set_state(state["generators"][name])


def save_checkpoint(run_dir: str | Path, step: int, state: dict[str, Any], keep: int = 2) -> Path:
    """Write ``state`` as the checkpoint of ``step`` atomically; keep the ``keep`` newest.

    Args:
        run_dir: the run folder.
        step: optimiser steps done.
        state: tensors and plain values only.
        keep: checkpoints to keep (older ones are deleted after the new one is in place).

    Returns:
        The checkpoint's path.
    """
    from byoc_cli.io.atomic import atomic_write_bytes

    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "step": int(step),
        **state,
    }
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    path = checkpoint_path(run_dir, step)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, buffer.getvalue())
    for old_step, old_path in list_checkpoints(run_dir)[:-keep]:
        if old_step != step:
            old_path.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read one checkpoint (never unpickles code).

    Raises:
        InputError: missing, unreadable or not a checkpoint.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such checkpoint")
    try:
        with open_input(path, "checkpoint") as f:
            state = torch.load(f, map_location="cpu", weights_only=True)
    except InputError:
        raise
    except Exception as exc:  # truncated / corrupt archives raise various errors
        raise InputError(path, f"unreadable checkpoint ({type(exc).__name__})") from exc
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise InputError(path, "not a byoc training checkpoint")
    if state.get("version") != CHECKPOINT_VERSION:
        raise InputError(path, f"unsupported checkpoint version {state.get('version')!r}")
    return state


def load_latest_checkpoint(run_dir: str | Path) -> tuple[dict[str, Any], Path] | None:
    """The newest readable checkpoint of a run (an unreadable newest one is skipped).

    Returns:
        ``(state, path)``, or None when the run has no checkpoint.
    """
    errors = []
    for _step, path in reversed(list_checkpoints(run_dir)):
        try:
            return load_checkpoint(path), path
        except InputError as exc:
            errors.append(exc)
    if errors:
        raise errors[0]
    return None
