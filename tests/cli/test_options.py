"""Shared option types: every float option of every command refuses nan and inf as a usage
error naming the option; seeds are bounded to what a generator takes."""

from __future__ import annotations

import logging

import click
import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli
from byoc_cli.cli.options import MAX_SEED, FiniteFloat, finite_float


def _commands() -> dict[str, click.Command]:
    ctx = click.Context(cli)
    out = {}
    for name in cli.list_commands(ctx):
        command = cli.get_command(ctx, name)
        if isinstance(command, click.Group):
            sub = click.Context(command, parent=ctx)
            for child in command.list_commands(sub):
                out[f"{name} {child}"] = command.get_command(sub, child)
        else:
            out[name] = command
    return out


def _options(kind) -> list[tuple[str, str]]:
    return [
        (name, param.opts[-1])
        for name, command in sorted(_commands().items())
        for param in command.params
        if isinstance(param, click.Option) and isinstance(param.type, kind)
    ]


FLOAT_OPTIONS = _options(click.FloatRange) + _options(type(click.FLOAT))


def test_every_float_option_is_finite():
    assert FLOAT_OPTIONS, "no float option found"
    assert len(FLOAT_OPTIONS) >= 12
    for name, option in FLOAT_OPTIONS:
        command = _commands()[name]
        param = next(p for p in command.params if option in p.opts)
        assert isinstance(param.type, FiniteFloat), f"{name} {option}"


@pytest.mark.parametrize(("command", "option"), FLOAT_OPTIONS)
@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "NaN"])
def test_nan_and_inf_are_usage_errors_naming_the_option(command, option, value):
    result = CliRunner().invoke(cli, [*command.split(), f"{option}={value}"])
    assert result.exit_code == 2, result.output
    assert f"'{option}'" in result.stderr and "not a finite number" in result.stderr


@pytest.mark.parametrize(
    ("command", "option"), [c for c in _options(click.IntRange) if c[1] == "--seed"]
)
def test_seed_beyond_64_bits_is_a_usage_error(command, option):
    result = CliRunner().invoke(cli, [*command.split(), option, str(MAX_SEED + 1)])
    assert result.exit_code == 2 and "'--seed'" in result.stderr
    assert "Traceback" not in result.output


def test_finite_float_keeps_the_range():
    kind = finite_float(0, 1)
    assert kind.convert("0.5", None, None) == 0.5
    with pytest.raises(click.BadParameter):
        kind.convert("1.5", None, None)
    with pytest.raises(click.BadParameter, match="not a finite number"):
        kind.convert(float("nan"), None, None)


@pytest.mark.parametrize("name", sorted(_commands()))
def test_every_command_takes_and_lists_v_and_q(name):
    help_text = CliRunner().invoke(cli, [*name.split(), "--help"]).output
    assert "-v, --verbose" in help_text and "-q, --quiet" in help_text, name


@pytest.mark.parametrize(
    ("before", "after", "level"),
    [
        ([], [], logging.WARNING),
        ([], ["-v"], logging.INFO),
        (["-v"], ["-v"], logging.DEBUG),
        ([], ["-vv"], logging.DEBUG),
        ([], ["-q"], logging.ERROR),
        (["-q"], ["-v"], logging.ERROR),
        (["-v"], ["--quiet"], logging.ERROR),
    ],
)
def test_v_and_q_after_the_command_set_the_log_level_as_before_it(tmp_path, before, after, level):
    out = tmp_path / "w.safetensors"
    args = [*before, "weights", "init", "-o", str(out), *after]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.stderr
    assert logging.getLogger().getEffectiveLevel() == level
