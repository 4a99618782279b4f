"""The ``byoc`` command: a Click group whose subcommands import their heavy modules lazily."""

from __future__ import annotations

import importlib

import click

from byoc_cli import __version__
from byoc_cli.cli.options import verbosity_options
from byoc_cli.threads import apply_thread_policy, keep_freed_memory, set_wait_policy

# OpenMP reads its wait policy once, when torch first loads it: before any command runs
set_wait_policy()
keep_freed_memory()

# subcommand name -> (module, attribute); imported only when the command runs or --help asks
_COMMANDS = {
    "register": ("byoc_cli.cli.register", "register"),
    "register-batch": ("byoc_cli.cli.batch", "register_batch"),
    "features": ("byoc_cli.cli.features", "features"),
    "weights": ("byoc_cli.cli.weights", "weights"),
    "train": ("byoc_cli.cli.train", "train"),
    "eval-fmr": ("byoc_cli.cli.evaluate", "eval_fmr"),
    "eval-pairs": ("byoc_cli.cli.evaluate", "eval_pairs"),
    "make-fragments": ("byoc_cli.cli.fragments", "make_fragments"),
    "register-scans": ("byoc_cli.cli.scans", "register_scans"),
    "odometry": ("byoc_cli.cli.odometry", "odometry"),
}


class LazyGroup(click.Group):
    """A group that imports a subcommand's module only when it is used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(name for name in _COMMANDS if self._available(name))

    @staticmethod
    def _available(name: str) -> bool:
        module = _COMMANDS[name][0]
        return importlib.util.find_spec(module) is not None

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in _COMMANDS or not self._available(name):
            return None
        module, attr = _COMMANDS[name]
        return getattr(importlib.import_module(module), attr)


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
    error, 3 registered below the confidence gate. -v and -q work before or after the
    command's name.
    """


def main() -> None:
    """Console-script entry point."""
    cli(prog_name="byoc")


if __name__ == "__main__":  # pragma: no cover
    main()
