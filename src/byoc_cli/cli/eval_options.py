"""What ``eval-fmr`` and ``eval-pairs`` share: ``--method a b c``, the common options, and
one :class:`EvalRun` that checks them, builds the methods and writes the outputs."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.display import is_quiet
from byoc_cli.cli.options import (
    LENGTH,
    VOXEL,
    apply,
    device_option,
    float_option,
    int_option,
    path_option,
    quiet_option,
    resolve_device,
    seed_option,
    verbose_option,
)
from byoc_cli.cli.output import claim_outputs, write_json
from byoc_cli.pipeline.recipe import PRESETS

#: ``--method`` when none is given.
DEFAULT_METHODS = ("byoc", "fpfh-ransac")
_METHOD_FLAG = "--method"


def _known_methods() -> tuple[str, ...]:
    from byoc_cli.evaluation.method_names import METHOD_NAMES

    return METHOD_NAMES


def _is_method_list(token: str) -> bool:
    parts = token.replace(",", " ").split()
    return bool(parts) and all(p in _known_methods() for p in parts)


def expand_method_args(args: Sequence[str]) -> list[str]:
    """Let ``--method a b c`` mean ``--method a --method b --method c``.

    After ``--method VALUE`` (or ``--method=VALUE``), the following tokens that are method
    names (or comma lists of them) are taken as more values; the first other token ends the
    list. ``--`` ends option processing as usual.
    """
    out: list[str] = []
    k = 0
    args = list(args)
    while k < len(args):
        token = args[k]
        if token == "--":
            out.extend(args[k:])
            break
        if token == _METHOD_FLAG and k + 1 < len(args):
            out += [token, args[k + 1]]
            k += 2
        elif token.startswith(_METHOD_FLAG + "="):
            out.append(token)
            k += 1
        else:
            out.append(token)
            k += 1
            continue
        while k < len(args) and _is_method_list(args[k]):
            out += [_METHOD_FLAG, args[k]]
            k += 1
    return out


_METHOD_HELP = (
    "Methods compared side by side, one table column each: {methods}. Several values: "
    "'--method byoc fpfh-ransac', commas or repeated --method "
    f"[default: {' '.join(DEFAULT_METHODS)}]."
)


class MethodOption(click.Option):
    """``--method``: its help lists the names of the method registry
    (``evaluation.methods.METHOD_NAMES``), read when the help is shown, so it cannot drift."""

    def get_help_record(self, ctx: click.Context) -> tuple[str, str] | None:
        self.help = _METHOD_HELP.format(methods=", ".join(_known_methods()))
        return super().get_help_record(ctx)


class EvalCommand(click.Command):
    """A command whose ``--method`` takes several space-separated values."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        return super().parse_args(ctx, expand_method_args(args))


eval_options = apply(
    click.option(
        "--method",
        "method",
        cls=MethodOption,
        multiple=True,
        metavar="NAME...",
    ),
    path_option(
        "--weights",
        multiple=True,
        help="Weights file for byoc; repeat to compare several (columns byoc[name], "
        "byoc[folder/name] when names repeat). "
        "None: the weights that ship with byoc-cli (--method byoc-random: a random "
        "compact encoder seeded with --seed).",
    ),
    path_option(
        "--json",
        "json_path",
        dash=True,
        help="Write every figure, per-pair results, protocols, settings and versions "
        "as JSON ('-' is stdout).",
    ),
    path_option(
        "--plot",
        "plot_path",
        help="Write a PNG of accuracy against threshold, all methods side by side.",
    ),
    path_option(
        "--cache-dir",
        file=False,
        help="Cache per-cloud features here (npz per cloud, feature settings and "
        "weights hash); a rerun reads them.",
    ),
    int_option("--limit", min=1, help="At most N pairs per scene / sequence (the first ones)."),
    float_option(
        "--fpfh-voxel-size",
        type=VOXEL,
        default=PRESETS["fpfh"].features.reference_voxel,
        help="Voxel size (m) of the FPFH methods (the fpfh recipe's by default).",
    ),
    float_option(
        "--icp-distance",
        type=LENGTH,
        default=0.10,
        help="ICP's largest correspondence distance (m); ICP starts from the identity.",
    ),
    seed_option,
    device_option,
    verbose_option,
    quiet_option("No progress bar and no table; only errors on stderr.", expose_value=True),
)


@dataclass
class EvalRun:
    """The common options of one evaluation run, checked (:meth:`start`)."""

    method: tuple[str, ...]
    weights: tuple[Path, ...]
    json_path: Path | None
    plot_path: Path | None
    cache_dir: Path | None
    limit: int | None
    fpfh_voxel_size: float
    icp_distance: float
    quiet: bool
    seed: int
    device: str

    def start(self, input_dirs: Sequence[Path | None]) -> None:
        """Check methods, device and outputs before any long work; sets ``names``."""
        from byoc_cli.evaluation.method_names import parse_method_names

        self.quiet = is_quiet(self.quiet)
        try:
            self.names = parse_method_names(self.method or DEFAULT_METHODS)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="'--method'") from None
        if self.weights and "byoc" not in self.names:
            raise click.UsageError("--weights is for --method byoc, which is not selected")
        self.device = resolve_device(self.device)
        self.outputs = claim_outputs(
            {"--json": self.json_path, "--plot": self.plot_path},
            inputs=self.weights,
            input_dirs=input_dirs,
        )

    def weights_files(self) -> list[Path]:
        """``--weights``, or the packaged weights for byoc when none is given."""
        from byoc_cli.cli.options import packaged_weights

        if self.weights or "byoc" not in self.names:
            return list(self.weights)
        packaged = packaged_weights()
        if packaged is None:
            raise click.UsageError(
                "--method byoc needs --weights FILE (this install ships no trained weights); "
                "--method byoc-random evaluates a random encoder"
            )
        return [packaged]  # loaded (checksum checked) by evaluation.methods

    def build_methods(self, **extra: Any) -> list:
        from byoc_cli.evaluation.methods import build_methods

        return build_methods(
            self.names,
            self.weights_files(),
            seed=self.seed,
            device=self.device,
            fpfh_voxel_size=self.fpfh_voxel_size,
            icp_distance=self.icp_distance,
            **extra,
        )

    def settings(self) -> dict[str, Any]:
        return {
            "cache_dir": str(self.cache_dir) if self.cache_dir else None,
            "device": self.device,
            "fpfh_voxel_size": self.fpfh_voxel_size,
            "icp_distance": self.icp_distance,
        }

    def write(self, report: dict[str, Any], plotter: Callable) -> None:
        """The plot and the JSON report, committed together (or neither)."""
        with self.outputs:
            if self.plot_path is not None:
                plotter(report, self.plot_path)
            write_json(self.json_path, report, indent=1)


def method_notes(methods) -> list[str]:
    """Notes under the table: which byoc columns are random encoders or the shipped weights."""
    from byoc_cli.pipeline.default_weights import default_weights_path

    shipped = default_weights_path()
    notes = []
    for m in methods:
        info = m.features.info if m.features is not None else {}
        if m.kind == "byoc" and info.get("source") == "random-init":
            notes.append(f"note: {m.name}: {info['note']}")
        elif m.kind == "byoc" and shipped is not None and info.get("path") == str(shipped):
            notes.append(
                f"note: {m.name}: the weights that ship with byoc-cli "
                f"({info['variant']}, {info['steps']} steps)"
            )
    return notes
