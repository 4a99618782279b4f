"""The ``byoc`` command: a Click group whose subcommands import their heavy modules lazily."""

from __future__ import annotations

import importlib
import importlib.util
from typing import NamedTuple

import click

from byoc_cli import __version__
from byoc_cli.cli.options import verbosity_options
from byoc_cli.threads import apply_thread_policy, keep_freed_memory, set_wait_policy

# OpenMP reads its wait policy once, when torch first loads it: before any command runs
set_wait_policy()
keep_freed_memory()


class CommandEntry(NamedTuple):
    """A subcommand in the registry: where it lives and the line ``byoc --help`` shows."""

    module: str
    attr: str
    short_help: str


# subcommand name -> its entry; the module is imported only when the command runs or its own
# --help asks (command modules import torch and open3d inside their functions), so that
# ``byoc --help`` reads this table alone
_COMMANDS = {
    "register": CommandEntry(
        "byoc_cli.cli.register", "register", "The transform mapping SOURCE into TARGET's frame."
    ),
    "register-batch": CommandEntry(
        "byoc_cli.cli.batch",
        "register_batch",
        "Many pairs in one process, with a JSON Lines summary.",
    ),
    "features": CommandEntry(
        "byoc_cli.cli.features",
        "features",
        "A cloud's kept points and descriptors, for other solvers.",
    ),
    "weights": CommandEntry(
        "byoc_cli.cli.weights", "weights", "Validate and describe a weights file, or make one."
    ),
    "train": CommandEntry(
        "byoc_cli.cli.train", "train", "Self-supervised training from RGB-D or depth video."
    ),
    "eval-fmr": CommandEntry(
        "byoc_cli.cli.evaluate",
        "eval_fmr",
        "Feature-match and registration recall on a 3DMatch layout.",
    ),
    "eval-pairs": CommandEntry(
        "byoc_cli.cli.evaluate",
        "eval_pairs",
        "Rotation, translation and chamfer accuracy on RGB-D video.",
    ),
    "make-fragments": CommandEntry(
        "byoc_cli.cli.fragments",
        "make_fragments",
        "A 3DMatch-layout benchmark from posed RGB-D video.",
    ),
    "register-scans": CommandEntry(
        "byoc_cli.cli.scans",
        "register_scans",
        "Many overlapping scans into one frame and one model.",
    ),
    "odometry": CommandEntry(
        "byoc_cli.cli.odometry",
        "odometry",
        "The camera trajectory of RGB-D video (TUM format).",
    ),
}


class LazyGroup(click.Group):
    """A group whose listing reads :data:`_COMMANDS` and that imports a subcommand's module
    only when that command is used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(name for name in _COMMANDS if self._available(name))

    @staticmethod
    def _available(name: str) -> bool:
        return importlib.util.find_spec(_COMMANDS[name].module) is not None

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in _COMMANDS or not self._available(name):
            return None
        entry = _COMMANDS[name]
        command = getattr(importlib.import_module(entry.module), entry.attr)
        command.short_help = entry.short_help
        return command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The command list of ``byoc --help``, from the registry (no command is imported)."""
        rows = [(name, _COMMANDS[name].short_help) for name in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


def _thread_policy(ctx: click.Context, param: click.Parameter, threads: int | None) -> None:
    """``--threads``: the thread policy of :mod:`byoc_cli.threads`, before any command."""
    apply_thread_policy(threads)


threads_option = click.option(
    "--threads",
    type=click.IntRange(min=1),
    expose_value=False,
    callback=_thread_policy,
    help="Threads for the numeric work [default: OMP_NUM_THREADS, else the cores this "
    "process may use: CPU affinity and cgroup quota]. Idle threads sleep after a short "
    "spin (OMP_WAIT_POLICY=PASSIVE, GOMP_SPINCOUNT=1000, unless set).",
)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="byoc")
@threads_option
@verbosity_options
def cli() -> None:
    """Register point clouds with features learned from raw RGB-D video (BYOC).

    Results (matrices, JSON) go to stdout or the files named; progress, tables and
    logs go to stderr. Exit codes: 0 success, 1 bad input or runtime error, 2 usage
    error, 3 registered below the confidence gate, ambiguous or inconsistent (T written
    all the same).
    -v and -q work before or after the command's name.
    """


def main() -> None:
    """Console-script entry point."""
    cli(prog_name="byoc")


if __name__ == "__main__":  # pragma: no cover
    main()
