"""What commands show on stderr: rich progress bars and tables (never on stdout)."""

from __future__ import annotations

import sys
from typing import Any


def countdown(
    completed: float, total: float | None, elapsed: float | None, since: float
) -> float | None:
    """Seconds left of a task: the mean time per item so far times the items left, as of its
    last advance (``completed`` items in ``elapsed`` seconds), less the ``since`` seconds
    that have passed from then; None before the first item. So the ETA of work in items of
    many seconds (``register-batch``'s pairs) counts down between them instead of standing."""
    if not completed or total is None or elapsed is None:
        return None
    left = elapsed * (total - completed) / completed
    return max(0.0, left - since)


def progress_bar(*fields: str) -> Any:
    """A started rich ``Progress`` on stderr: description, bar, done/total, then a text
    column for each of ``fields`` (format strings of the task), elapsed time and ETA (a
    :func:`countdown`).

    The caller ends it with ``progress.__exit__(None, None, None)``.
    """
    import time
    from datetime import timedelta

    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        ProgressColumn,
        TextColumn,
        TimeElapsedColumn,
    )
    from rich.text import Text

    class CountdownColumn(ProgressColumn):
        """The ETA of :func:`countdown`, per task."""

        def __init__(self) -> None:
            super().__init__()
            self.advanced: dict[Any, tuple[float, float | None, float]] = {}

        def render(self, task: Any) -> Text:
            now = time.monotonic()
            seen = self.advanced.get(task.id)
            if seen is None or seen[0] != task.completed:
                seen = (task.completed, task.elapsed, now)
                self.advanced[task.id] = seen
            left = countdown(seen[0], task.total, seen[1], now - seen[2])
            shown = "-:--:--" if left is None else str(timedelta(seconds=round(left)))
            return Text(shown, style="progress.remaining")

    progress = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        *(TextColumn(field) for field in fields),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        CountdownColumn(),
        console=Console(stderr=True),
    )
    progress.__enter__()
    return progress


def is_quiet(quiet: bool) -> bool:
    """``quiet`` or ``-q`` (given before or after the subcommand)."""
    from byoc_cli.cli.options import quiet_requested

    return quiet or quiet_requested()


def print_table(title: str, columns: list[str], rows: list[list[str]], notes: list[str]) -> None:
    """A table on stderr (cells and title as text, not rich markup), then ``notes``."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    width = None if sys.stderr.isatty() else max(100, 40 + 22 * (len(columns) - 1))
    console = Console(stderr=True, width=width, highlight=False)
    # labels such as byoc[run] and paths are text, not rich markup
    table = Table(title=escape(title), title_justify="left")
    for k, name in enumerate(columns):
        table.add_column(escape(name), justify="left" if k == 0 else "right", no_wrap=k == 0)
    for row in rows:
        table.add_row(*(escape(cell) for cell in row))
    console.print(table)
    for note in notes:
        console.print(note, markup=False)


class EvalDisplay:
    """Progress bars of the evaluation commands (only when stderr is a terminal and not
    quiet); the ``display`` the evaluation runners call."""

    def __init__(self, quiet: bool) -> None:
        self.enabled = not quiet and sys.stderr.isatty()
        self.progress = None
        self.tasks: dict[str, Any] = {}

    def __enter__(self) -> EvalDisplay:
        if self.enabled:
            self.progress = progress_bar()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.progress is not None:
            self.progress.__exit__(*exc)

    def start(self, task: str, total: int) -> None:
        if self.progress is not None and total:
            self.tasks[task] = self.progress.add_task(task, total=total)

    def advance(self, task: str, steps: int = 1) -> None:
        if self.progress is not None and task in self.tasks:
            self.progress.advance(self.tasks[task], steps)
