"""Divergence: a training step whose loss or weights are not finite ends the run.

A learning rate far too large (or an unlucky batch) turns the weights into NaN or Inf within
a step or two; the next forward pass then fails inside an SVD (``LinAlgError``) or returns a
NaN loss, and every checkpoint and exported weights file after that is garbage. The loops of
``trainer`` and ``self_posed`` run each step inside :func:`step_guard` and end with
:class:`~byoc_cli.errors.TrainingError` before anything diverged is saved.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator

import torch

from byoc_cli.errors import TrainingError

__all__ = ["check_finite", "step_guard"]


def _diverged(step: int, lr: float, what: str) -> TrainingError:
    return TrainingError(
        f"training diverged at step {step}: {what} (learning rate {lr:g}; try a smaller --lr)"
    )


def check_finite(
    loss: torch.Tensor, parameters: Iterable[torch.Tensor], step: int, lr: float
) -> None:
    """Raise unless ``loss`` and every tensor of ``parameters`` are finite.

    Args:
        loss: the step's scalar loss.
        parameters: the weights after the optimiser step.
        step: the step number, for the message.
        lr: the learning rate, for the message.

    Raises:
        TrainingError: naming the step and the learning rate.
    """
    if not bool(torch.isfinite(loss.detach()).all()):
        raise _diverged(step, lr, "the loss is NaN or Inf")
    for tensor in parameters:
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor.detach()).all()):
            raise _diverged(step, lr, "the weights hold NaN or Inf")


def _all_finite(parameters: Iterable[torch.Tensor]) -> bool:
    return all(bool(torch.isfinite(t.detach()).all()) for t in parameters if t.is_floating_point())


@contextlib.contextmanager
def step_guard(module: torch.nn.Module, step: int, lr: float) -> Iterator[None]:
    """Run one training step of ``module``; a ``LinAlgError`` (an SVD of NaN input) becomes
    :class:`TrainingError`, and so does a loss or weights that are not finite at the end
    (call :func:`check_finite` inside the block for the loss).

    Raises:
        TrainingError: "diverged" when the weights are not finite; otherwise the step's
            linear-algebra failure, on one line.
    """
    try:
        yield
    except torch.linalg.LinAlgError as exc:
        if not _all_finite(module.parameters()):
            raise _diverged(step, lr, "the weights hold NaN or Inf") from exc
        reason = " ".join(str(exc).split())[:200]
        raise TrainingError(f"training step {step} failed: {reason}") from exc
