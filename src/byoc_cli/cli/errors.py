"""Turning library errors into one-line messages and exit codes (the only place that does)."""

from __future__ import annotations

import functools
import logging
import os
import warnings
from collections.abc import Callable
from typing import Any

import click

from byoc_cli.errors import ByocError

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_LOW_CONFIDENCE = 3

log = logging.getLogger("byoc")


class CliError(click.ClickException):
    """Exit 1 with ``byoc: error: <message>`` on one line of stderr."""

    exit_code = EXIT_ERROR

    def format_message(self) -> str:
        return " ".join(str(self.message).split())

    def show(self, file: Any = None) -> None:
        try:
            click.echo(f"byoc: error: {self.format_message()}", err=True)
        except (OSError, ValueError):  # stderr closed or full: the exit code still tells
            pass


class StdoutError(CliError):
    """Standard output is closed, full or a broken pipe."""


def silence_stdout() -> None:
    """Point file descriptor 1 at /dev/null so that the exit flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.close(devnull)
    except OSError:
        pass


def _one_line_warning(message: Any, category: Any, *args: Any, **kwargs: Any) -> None:
    """Library warnings as our own one-line log messages (no file:line, no source line)."""
    log.warning("%s", " ".join(str(message).split()))


def handle_errors(func: Callable) -> Callable:
    """Decorate a command: typed library errors and write errors become :class:`CliError`
    (exit 1, one line) and warnings become one-line log messages."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            with warnings.catch_warnings():
                warnings.showwarning = _one_line_warning
                return func(*args, **kwargs)
        except StdoutError:
            silence_stdout()
            raise
        except (click.ClickException, click.exceptions.Exit, click.Abort):
            raise
        except ByocError as exc:
            raise CliError(str(exc)) from exc
        except MemoryError as exc:
            raise CliError("out of memory (try a larger --voxel-size or --max-points)") from exc
        except KeyboardInterrupt:
            raise click.Abort() from None
        except OSError as exc:  # a stream or file failed outside our typed readers/writers
            where = f"{exc.filename}: " if exc.filename else ""
            raise CliError(f"{where}{exc.strerror or exc}") from exc

    return wrapper
