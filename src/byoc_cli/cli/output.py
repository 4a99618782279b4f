"""Writing a command's results: standard output, JSON reports and the output policy.

Every command opens one :class:`~byoc_cli.io.outputs.OutputSet` (:func:`outputs`), claims
its output files before the work starts, writes them inside the ``with`` block and has them
committed together at its end; results for standard output go through :func:`write_stdout`,
which turns a closed, full or broken stdout into one line and exit 1.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.errors import StdoutError
from byoc_cli.errors import InputError
from byoc_cli.io.outputs import OutputSet, is_stdout

__all__ = [
    "check_binary_stdout",
    "claim_outputs",
    "is_stdout",
    "write_json",
    "write_stdout",
    "write_stdout_bytes",
]


def write_stdout(text: str) -> None:
    """Write ``text`` to standard output and flush it.

    Raises:
        StdoutError: stdout is closed, full (``/dev/full``) or a broken pipe.
    """
    stream = sys.stdout
    if stream is None:
        raise StdoutError("cannot write to stdout: it is closed")
    try:
        stream.write(text)
        stream.flush()
    except (OSError, ValueError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        raise StdoutError(f"cannot write to stdout: {reason}") from exc


def check_binary_stdout(path: Path | None, option: str) -> None:
    """Refuse binary output to standard output (``option`` is ``-``) when stdout is a
    terminal, where it would be garbage (gzip refuses the same way); call before the work.

    Raises:
        click.UsageError: naming ``option``.
    """
    if is_stdout(path) and sys.stdout is not None and sys.stdout.isatty():
        raise click.UsageError(
            f"{option} -: not writing binary data to a terminal; redirect stdout"
        )


def write_stdout_bytes(data: bytes) -> None:
    """Write binary ``data`` to standard output and flush it.

    Raises:
        StdoutError: stdout is closed, full or a broken pipe.
    """
    stream = getattr(sys.stdout, "buffer", None)
    if stream is None:
        raise StdoutError("cannot write to stdout: it is closed or not binary")
    try:
        sys.stdout.flush()
        stream.write(data)
        stream.flush()
    except (OSError, ValueError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        raise StdoutError(f"cannot write to stdout: {reason}") from exc


def write_json(path: Path | None, value: Any, indent: int = 2, sort_keys: bool = False) -> None:
    """Write ``value`` as strict JSON (NaN/Inf as null) to ``path`` (``-``: stdout)."""
    from byoc_cli.io import atomic_write_text
    from byoc_cli.io.jsonout import strict_dumps

    if path is None:
        return
    text = strict_dumps(value, indent=indent, sort_keys=sort_keys) + "\n"
    if is_stdout(path):
        write_stdout(text)
    else:
        atomic_write_text(path, text)


def _takes_stdout(option: str) -> bool:
    """True when the running command's ``option`` accepts ``-`` (standard output)."""
    ctx = click.get_current_context(silent=True)
    for param in ctx.command.params if ctx is not None else ():
        if option in getattr(param, "opts", ()):
            return bool(getattr(param.type, "allow_dash", False))
    return False


def claim_outputs(
    outputs: dict[str, Path | None],
    inputs: Iterable[Path | None] = (),
    input_dirs: Iterable[Path | None] = (),
) -> OutputSet:
    """An :class:`OutputSet` with every output of ``outputs`` (option -> path) claimed.

    At most one of them may be ``-`` (stdout); ``/dev/stdout`` means the same stream for an
    option that takes ``-``.

    Raises:
        click.UsageError: two outputs are ``-``.
        InputError: the output policy refuses one of them (``/dev/stdout`` for an option
            that does not take ``-``, ``/dev/stderr`` for any).
    """
    to_stdout = [name for name, path in outputs.items() if is_stdout(path)]
    if len(to_stdout) > 1:
        raise click.UsageError(f"{' and '.join(to_stdout)} cannot both be stdout")
    for name in to_stdout:
        if str(outputs[name]) != "-" and not _takes_stdout(name):
            raise InputError(outputs[name], f"is standard output, which {name} does not take")
    out = OutputSet(inputs, input_dirs)
    for path in outputs.values():
        out.claim(None if is_stdout(path) else path)  # stdout: checked above
    return out


def main_output(output: Path, json_path: Path | None) -> Path | None:
    """``-o`` of a command whose main output defaults to stdout beside ``--json``: None when
    only ``--json -`` was asked for (the default ``-o -`` then yields).

    Raises:
        click.UsageError: ``-o`` and ``--json`` both stdout, both given.
    """
    from click.core import ParameterSource

    if not (is_stdout(output) and is_stdout(json_path)):
        return output
    if click.get_current_context().get_parameter_source("output") is ParameterSource.DEFAULT:
        return None
    raise click.UsageError("-o and --json cannot both be stdout")
