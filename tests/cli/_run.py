"""Helpers of the command tests that run `byoc` in process."""

from __future__ import annotations

from click.testing import CliRunner

from byoc_cli.cli.main import cli


def invoke(args: list) -> object:
    """``byoc ARGS`` (paths and numbers as strings) in a fresh :class:`CliRunner`."""
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_error_line(result, *needles: str) -> None:
    """``result`` printed exactly one ``byoc: error:`` line, holding every needle."""
    lines = [ln for ln in result.stderr.splitlines() if ln.startswith("byoc: error:")]
    assert len(lines) == 1, result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
