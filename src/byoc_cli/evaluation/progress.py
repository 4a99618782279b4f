"""Progress reporting from the evaluation runners (the CLI draws it; the runners only call)."""

from __future__ import annotations

from typing import Protocol

__all__ = ["NullProgress", "Progress"]


class Progress(Protocol):
    """Receives the runners' progress: named tasks with a total, advanced one step at a time."""

    def start(self, task: str, total: int) -> None:
        """A task of ``total`` steps begins (``features``, ``pairs``)."""

    def advance(self, task: str, steps: int = 1) -> None:
        """``steps`` more steps of ``task`` are done."""


class NullProgress:
    """Progress that goes nowhere."""

    def start(self, task: str, total: int) -> None:
        pass

    def advance(self, task: str, steps: int = 1) -> None:
        pass
