"""The ``byoc`` group: its command registry, and help that never loads the numeric stack."""

from __future__ import annotations

import json
import subprocess
import sys

import click
from click.testing import CliRunner

from byoc_cli.cli.main import _COMMANDS, cli

#: modules that ``--help`` must leave unloaded (torch and open3d take seconds; numpy would
#: double the time of ``byoc COMMAND --help`` against ``byoc --version``)
HEAVY = ("torch", "open3d", "numpy")

_PROBE = r"""
import json, sys
from byoc_cli.cli.main import cli
commands, heavy = json.loads(sys.argv[1]), json.loads(sys.argv[2])
loaded = {}
for args in commands:
    try:
        cli.main([*args, "--help"], prog_name="byoc", standalone_mode=False)
    except SystemExit:
        pass
    found = [m for m in heavy if m in sys.modules]
    if found:
        loaded[" ".join(args) or "byoc"] = found
        break
ours = sorted(m for m in sys.modules if m.startswith("byoc_cli.cli."))
print(json.dumps({"loaded": loaded, "modules": ours}))
"""


def _probe(commands: list[list[str]]) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", _PROBE, json.dumps(commands), json.dumps(HEAVY)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.splitlines()[-1])


def _every_command() -> list[list[str]]:
    ctx = click.Context(cli)
    out = []
    for name in cli.list_commands(ctx):
        out.append([name])
        command = cli.get_command(ctx, name)
        if isinstance(command, click.Group):
            out += [[name, child] for child in command.list_commands(click.Context(command))]
    return out


def test_top_level_help_imports_no_command_module():
    found = _probe([[]])
    assert found["loaded"] == {}
    assert set(found["modules"]) <= {"byoc_cli.cli.main", "byoc_cli.cli.options"}


def test_every_command_help_leaves_torch_open3d_and_numpy_unloaded():
    commands = _every_command()
    assert len(commands) >= len(_COMMANDS) + 2  # weights info, weights init
    found = _probe(commands)
    assert found["loaded"] == {}, f"--help loaded {found['loaded']}"


def test_the_listing_is_the_registry():
    result = CliRunner().invoke(cli, ["--help"])
    assert result.exit_code == 0
    listing = result.output.split("Commands:")[1]
    for name, entry in _COMMANDS.items():
        assert f"  {name} " in listing
        assert " ".join(entry.short_help.split()[:4]) in " ".join(listing.split())


def test_every_registered_command_loads_with_its_registry_line():
    ctx = click.Context(cli)
    for name, entry in _COMMANDS.items():
        command = cli.get_command(ctx, name)
        assert isinstance(command, click.Command) and command.name == name
        assert command.get_short_help_str(limit=200) == entry.short_help
    assert cli.get_command(ctx, "no-such-command") is None


def test_an_unknown_command_is_a_usage_error():
    result = CliRunner().invoke(cli, ["regster"])
    assert result.exit_code == 2
    assert "No such command 'regster'" in result.output
