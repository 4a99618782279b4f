"""Turning library errors into one-line messages and exit codes (the only place that does)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import click

from byoc_cli.errors import ByocError

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_LOW_CONFIDENCE = 3


class CliError(click.ClickException):
    """Exit 1 with ``byoc: error: <message>`` on one line of stderr."""

    exit_code = EXIT_ERROR

    def format_message(self) -> str:
        return " ".join(str(self.message).split())

    def show(self, file: Any = None) -> None:
        click.echo(f"byoc: error: {self.format_message()}", err=True)


def handle_errors(func: Callable) -> Callable:
    """Decorate a command so typed library errors become :class:`CliError` (exit 1)."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except (click.ClickException, click.exceptions.Exit, click.Abort):
            raise
        except ByocError as exc:
            raise CliError(str(exc)) from exc
        except MemoryError as exc:
            raise CliError("out of memory (try a larger --voxel-size or --max-points)") from exc
        except KeyboardInterrupt:
            raise click.Abort() from None

    return wrapper
