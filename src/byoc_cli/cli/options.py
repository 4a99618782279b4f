"""Options shared by several commands, and the parameter types every command uses.

Numbers: :class:`FiniteFloat` refuses ``nan`` and ``inf`` (click's ``FloatRange`` lets them
through), :data:`SEED` is bounded to what a generator takes (0 to 2**64 - 1); both are usage
errors (exit 2) naming the option. Every float option takes one of the bounded kinds below
(:data:`VOXEL`, :data:`LENGTH`, :data:`SCALE`, :data:`DEPTH_SCALE`, :data:`DEGREES`,
:data:`LEARNING_RATE`; :data:`POSITIVE` otherwise), whose ranges are those of
:mod:`byoc_cli.limits`. :func:`float_option`, :func:`int_option` and :func:`path_option`
declare an option in one line; a file option refuses a name ending in ``/`` (a folder's).
:data:`verbosity_options` gives a command the root group's ``-v``/``-q``, so that they work
after the subcommand too.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from byoc_cli import limits

#: Largest seed a ``torch.Generator`` takes.
MAX_SEED = 2**64 - 1


class FiniteFloat(click.FloatRange):
    """A float in a range that must also be finite (no ``nan``, ``inf``)."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None):
        number = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return super().convert(number, param, ctx)


def finite_float(
    min: float | None = None,
    max: float | None = None,
    *,
    min_open: bool = False,
    max_open: bool = False,
) -> FiniteFloat:
    """A :class:`FiniteFloat` parameter type."""
    return FiniteFloat(min=min, max=max, min_open=min_open, max_open=max_open)


#: a voxel size in metres (features, ICP, merged model, FPFH)
VOXEL = finite_float(limits.MIN_VOXEL_SIZE, limits.MAX_VOXEL_SIZE)
#: a TSDF voxel in metres
TSDF_VOXEL = finite_float(limits.MIN_TSDF_VOXEL, limits.MAX_TSDF_VOXEL)
#: a distance, depth or truncation in metres
LENGTH = finite_float(limits.MIN_LENGTH, limits.MAX_LENGTH)
#: ``--scale``: input units to metres
SCALE = finite_float(limits.MIN_SCALE, limits.MAX_SCALE)
#: depth-image units per metre
DEPTH_SCALE = finite_float(limits.MIN_DEPTH_SCALE, limits.MAX_DEPTH_SCALE)
#: an angle in degrees, > 0
DEGREES = finite_float(0, limits.MAX_DEGREES, min_open=True)
#: Adam's learning rate
LEARNING_RATE = finite_float(0, limits.MAX_LR, min_open=True)
#: any other positive number
POSITIVE = finite_float(limits.MIN_POSITIVE, limits.MAX_POSITIVE)
SEED = click.IntRange(0, MAX_SEED)


def float_option(*decls: str, type: click.ParamType, **kwargs: Any) -> Callable:
    """A float option of a bounded kind (:data:`VOXEL`, :data:`LENGTH`, ...; always finite)."""
    kwargs.setdefault("show_default", kwargs.get("default") is not None)
    return click.option(*decls, type=type, **kwargs)


def int_option(*decls: str, min: int = 0, max: int | None = None, **kwargs: Any) -> Callable:
    """An integer option of at least ``min`` (and at most ``max``)."""
    kwargs.setdefault("show_default", kwargs.get("default") is not None)
    return click.option(*decls, type=click.IntRange(min=min, max=max), **kwargs)


class FilePath(click.Path):
    """A file path (not a folder); a name ending in ``/`` is refused, as ``cp`` and ``touch``
    refuse it: it names a folder, and ``Path`` would silently drop the slash."""

    def __init__(self, allow_dash: bool = False) -> None:
        super().__init__(dir_okay=False, path_type=Path, allow_dash=allow_dash)

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None):
        text = os.fsdecode(value) if isinstance(value, bytes | os.PathLike) else value
        if isinstance(text, str) and text.endswith(("/", os.sep)) and text != "-":
            self.fail(f"{text!r} ends with '/' (a folder); give a file name.", param, ctx)
        return super().convert(value, param, ctx)


def path_option(*decls: str, file: bool = True, **kwargs: Any) -> Callable:
    """A path option (``file=True``: a file, not a folder; ``dash=True``: ``-`` is stdio)."""
    dash = kwargs.pop("dash", False)
    if file:
        kind: click.Path = FilePath(allow_dash=dash)
    else:
        kind = click.Path(path_type=Path, allow_dash=dash)
    return click.option(*decls, type=kind, **kwargs)


def choice_option(*decls: str, choices: list[str], **kwargs: Any) -> Callable:
    """An option taking one of ``choices``."""
    kwargs.setdefault("show_default", kwargs.get("default") is not None)
    return click.option(*decls, type=click.Choice(choices), **kwargs)


def apply(*options: Callable) -> Callable:
    """One decorator out of several option decorators (in reading order)."""

    def decorate(func: Callable) -> Callable:
        for option in reversed(options):
            func = option(func)
        return func

    return decorate


#: an explicit ``--voxel-size`` of a command with ``auto``: in the units of the points,
#: so any length a cloud may be in (millimetres included)
VOXEL_ANY_UNIT = LENGTH


class VoxelSize(click.ParamType):
    """``auto`` or a length (:data:`VOXEL_ANY_UNIT`)."""

    name = "auto|FLOAT"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None):
        if value is None or value == "auto":
            return value
        return VOXEL_ANY_UNIT.convert(value, param, ctx)


seed_option = click.option(
    "--seed",
    type=SEED,
    default=0,
    show_default=True,
    help="Seeds every random choice; the same seed gives the same result.",
)
DEVICES = ["auto", "cpu", "cuda"]
device_option = choice_option(
    "--device",
    choices=DEVICES,
    default="auto",
    help="Where the encoder runs (auto: cuda when available).",
)


def resolve_device(device: str) -> str:
    """``auto`` -> ``cuda`` when available else ``cpu``; ``cuda`` without CUDA is a usage error."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise click.BadParameter("CUDA is not available on this machine", param_hint="'--device'")
    return device


def packaged_weights() -> Path | None:
    """The weights file shipped inside the package, if this install ships one."""
    from byoc_cli.pipeline.default_weights import default_weights_path

    return default_weights_path()


#: key of the root context's ``meta`` that holds ``-v``/``-q``, wherever they were given
_VERBOSITY = "byoc.verbosity"
QUIET_HELP = "Only errors on stderr."


def set_verbosity(ctx: click.Context, verbose: int = 0, quiet: bool = False) -> None:
    """Record ``-v`` (counted) and ``-q`` given to the root group or to a subcommand, and set
    the log level of stderr from all of them: ``-q`` errors only, else warnings, ``-v`` info,
    ``-vv`` debug."""
    state = ctx.find_root().meta.setdefault(_VERBOSITY, {"verbose": 0, "quiet": False})
    state["verbose"] += verbose
    state["quiet"] = state["quiet"] or quiet
    levels = (logging.WARNING, logging.INFO, logging.DEBUG)
    level = logging.ERROR if state["quiet"] else levels[min(state["verbose"], 2)]
    logging.basicConfig(level=level, format="byoc: %(levelname)s: %(message)s", force=True)
    logging.captureWarnings(True)


def quiet_requested() -> bool:
    """True when ``-q`` was given, before or after the subcommand."""
    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return False
    return bool(ctx.find_root().meta.get(_VERBOSITY, {}).get("quiet"))


def _on_verbose(ctx: click.Context, param: click.Parameter, value: int) -> int:
    set_verbosity(ctx, verbose=value)
    return value


def _on_quiet(ctx: click.Context, param: click.Parameter, value: bool) -> bool:
    set_verbosity(ctx, quiet=value)
    return value


verbose_option = click.option(
    "-v",
    "--verbose",
    count=True,
    expose_value=False,
    callback=_on_verbose,
    help="More log output on stderr (-vv for debug).",
)


def quiet_option(help: str = QUIET_HELP, expose_value: bool = False) -> Callable:
    """``-q/--quiet``: errors only on stderr (the log level), plus what ``help`` says the
    command leaves out; ``expose_value`` passes it to the command as ``quiet``."""
    return click.option(
        "-q", "--quiet", is_flag=True, expose_value=expose_value, callback=_on_quiet, help=help
    )


#: ``-v``/``-q`` for a command that has no quiet mode of its own.
verbosity_options = apply(verbose_option, quiet_option())
