"""``byoc eval-fmr`` and ``byoc eval-pairs``: methods side by side on the same pairs.

Tables and progress go to stderr; ``--json`` writes every figure (``-`` is stdout, which is
otherwise left empty); ``--plot`` writes a PNG of accuracy against threshold.
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.errors import handle_errors
from byoc_cli.cli.options import device_option, resolve_device, seed_option

log = logging.getLogger("byoc")

#: ``--method`` when none is given.
DEFAULT_METHODS = ("byoc", "fpfh-ransac")
_METHOD_FLAG = "--method"


def _known_methods() -> tuple[str, ...]:
    from byoc_cli.evaluation.methods import METHOD_NAMES

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


class EvalCommand(click.Command):
    """A command whose ``--method`` takes several space-separated values."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        return super().parse_args(ctx, expand_method_args(args))


def _methods_option(func):
    return click.option(
        "--method",
        "method",
        multiple=True,
        metavar="NAME...",
        help="Methods compared side by side, one table column each: byoc, fpfh-ransac, "
        "fpfh-procrustes, icp-point, icp-plane, identity. Several values: "
        "'--method byoc fpfh-ransac', commas or repeated --method "
        f"[default: {' '.join(DEFAULT_METHODS)}].",
    )(func)


def _common_options(func):
    options = [
        click.option(
            "--weights",
            multiple=True,
            type=click.Path(dir_okay=False, path_type=Path),
            help="Weights file for byoc; repeat to compare several (columns byoc[name], "
            "byoc[folder/name] when names repeat). "
            "None: a random compact encoder seeded with --seed.",
        ),
        click.option(
            "--json",
            "json_path",
            type=click.Path(dir_okay=False, allow_dash=True, path_type=Path),
            default=None,
            help="Write every figure, per-pair results, protocols, settings and versions "
            "as JSON ('-' is stdout).",
        ),
        click.option(
            "--plot",
            "plot_path",
            type=click.Path(dir_okay=False, path_type=Path),
            default=None,
            help="Write a PNG of accuracy against threshold, all methods side by side.",
        ),
        click.option(
            "--cache-dir",
            type=click.Path(file_okay=False, path_type=Path),
            default=None,
            help="Cache per-cloud features here (npz per cloud, feature settings and "
            "weights hash); a rerun reads them.",
        ),
        click.option(
            "--limit",
            type=click.IntRange(min=1),
            default=None,
            help="At most N pairs per scene / sequence (the first ones).",
        ),
        click.option(
            "--fpfh-voxel-size",
            type=click.FloatRange(min=0, min_open=True),
            default=0.05,
            show_default=True,
            help="Voxel size (m) of the FPFH methods.",
        ),
        click.option(
            "--icp-distance",
            type=click.FloatRange(min=0, min_open=True),
            default=0.10,
            show_default=True,
            help="ICP's largest correspondence distance (m); ICP starts from the identity.",
        ),
        click.option("--quiet", is_flag=True, help="No progress bar and no table on stderr."),
        seed_option,
        device_option,
    ]
    for option in reversed(options):
        func = option(func)
    return _methods_option(func)


# ================================================================== helpers


def _resolve_methods(method: tuple[str, ...], weights: tuple[Path, ...]) -> list[str]:
    from byoc_cli.evaluation.methods import parse_method_names

    try:
        names = parse_method_names(method or DEFAULT_METHODS)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--method'") from None
    if weights and "byoc" not in names:
        raise click.UsageError("--weights is for --method byoc, which is not selected")
    return names


def _weights_files(names: list[str], weights: tuple[Path, ...]) -> list[Path]:
    from byoc_cli.cli.options import packaged_weights

    if weights or "byoc" not in names:
        return list(weights)
    packaged = packaged_weights()
    return [packaged] if packaged is not None else []


def _check_output(path: Path | None) -> None:
    """Fail before a long run when an output file cannot be written."""
    from byoc_cli.errors import InputError

    if path is None or str(path) == "-":
        return
    if path.is_dir():
        raise InputError(path, "cannot write: is a directory")
    if not path.parent.is_dir():
        raise InputError(path, "cannot write: the folder does not exist")


def _is_quiet(quiet: bool) -> bool:
    ctx = click.get_current_context(silent=True)
    root = ctx.find_root() if ctx is not None else None
    return quiet or bool(root is not None and root.params.get("quiet"))


class _Display:
    """Rich progress bars on stderr (only when stderr is a terminal and not quiet)."""

    def __init__(self, quiet: bool) -> None:
        self.enabled = not quiet and sys.stderr.isatty()
        self.progress = None
        self.tasks: dict[str, Any] = {}

    def __enter__(self) -> _Display:
        if self.enabled:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self.progress = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=Console(stderr=True),
            )
            self.progress.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.progress is not None:
            self.progress.__exit__(*exc)

    def start(self, task: str, total: int) -> None:
        if self.progress is not None and total:
            self.tasks[task] = self.progress.add_task(task, total=total)

    def advance(self, task: str, steps: int = 1) -> None:
        if self.progress is not None and task in self.tasks:
            self.progress.advance(self.tasks[task], steps)


def _print_table(title: str, columns: list[str], rows: list[list[str]], notes: list[str]) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    width = None if sys.stderr.isatty() else max(100, 40 + 22 * (len(columns) - 1))
    console = Console(stderr=True, width=width, highlight=False)
    # labels such as byoc[run] and paths are text, not rich markup
    table = Table(title=escape(title), title_justify="left")
    for k, name in enumerate(columns):
        table.add_column(escape(name), justify="left" if k == 0 else "right", no_wrap=k == 0)
    for row in rows:
        table.add_row(*(escape(cell) for cell in row))
    console.print(table)
    for note in notes:
        console.print(note, markup=False)


def _write_outputs(report: dict[str, Any], json_path: Path | None, plot_path, plotter) -> None:
    from byoc_cli.io import atomic_write_text

    if plot_path is not None:
        plotter(report, plot_path)
    if json_path is not None:
        text = json.dumps(report, indent=1) + "\n"
        if str(json_path) == "-":
            sys.stdout.write(text)
            sys.stdout.flush()
        else:
            atomic_write_text(json_path, text)


def _method_notes(methods) -> list[str]:
    notes = []
    for m in methods:
        info = m.features.info if m.features is not None else {}
        if m.kind == "byoc" and info.get("source") == "random-init":
            notes.append(f"note: {m.name}: {info['note']}")
    return notes


# ================================================================== eval-fmr


@click.command(
    "eval-fmr",
    cls=EvalCommand,
    epilog="Protocols: FMR per scene with mean and std over scenes (FCGF) and pooled over "
    "all pairs (BYOC); registration recall from gt.info (RMSE <= 0.2 m, pairs j-i > 1). "
    "Exit codes: 0 done; 1 bad input (missing folder or fragment, malformed gt.log); "
    "2 usage error.",
)
@click.argument("root", type=click.Path(path_type=Path))
@click.option(
    "--gt-dir",
    type=click.Path(path_type=Path),
    default=None,
    help="Ground-truth folder (<scene>/gt.info or <scene>-evaluation/gt.info, e.g. "
    "benchmarks/3DMatch) for what ROOT lacks, typically gt.info.",
)
@click.option(
    "--scenes",
    multiple=True,
    metavar="NAME[,NAME...]",
    help="Only these scenes (repeat or comma-separate).",
)
@click.option(
    "--allow-missing",
    is_flag=True,
    help="Skip pairs whose fragment is missing (counted in the report) instead of failing.",
)
@click.option(
    "--num-samples",
    type=click.IntRange(min=0),
    default=5000,
    show_default=True,
    help="Points sampled per fragment for FMR and registration (0 = all).",
)
@click.option(
    "--tau1",
    type=click.FloatRange(min=0, min_open=True),
    default=0.10,
    show_default=True,
    help="FMR inlier distance (m).",
)
@click.option(
    "--tau2",
    type=click.FloatRange(0, 1),
    default=0.05,
    show_default=True,
    help="FMR inlier-ratio threshold.",
)
@click.option(
    "--top-k",
    type=click.IntRange(min=1),
    default=200,
    show_default=True,
    help="Ratio-test correspondences per direction for the 'corr' FMR.",
)
@_common_options
@handle_errors
def eval_fmr(
    root: Path,
    gt_dir: Path | None,
    scenes: tuple[str, ...],
    allow_missing: bool,
    num_samples: int,
    tau1: float,
    tau2: float,
    top_k: int,
    method: tuple[str, ...],
    weights: tuple[Path, ...],
    json_path: Path | None,
    plot_path: Path | None,
    cache_dir: Path | None,
    limit: int | None,
    fpfh_voxel_size: float,
    icp_distance: float,
    quiet: bool,
    seed: int,
    device: str,
) -> None:
    """Feature-match recall and registration on a 3DMatch-layout benchmark ROOT
    (ROOT/<scene>/cloud_bin_K.ply, ROOT/<scene>-evaluation/gt.log; 3DMatch or 3DLoMatch).

    Every gt.log pair (its matrix maps fragment j into fragment i) is scored with every
    method: FMR (tau1 0.10 m, tau2 0.05, 5000 sampled points), FMR of the top-k ratio-test
    correspondences, inlier ratios, registration recall (needs gt.info), success rate and
    rotation / translation errors.
    """
    from byoc_cli.errors import DatasetError
    from byoc_cli.evaluation.cache import FeatureCache
    from byoc_cli.evaluation.fmr import FmrConfig, evaluate_fmr, load_benchmark_pairs
    from byoc_cli.evaluation.methods import build_methods
    from byoc_cli.evaluation.plot import plot_fmr
    from byoc_cli.evaluation.report import fmr_report, fmr_table
    from byoc_cli.io.threedmatch import discover_benchmark

    quiet = _is_quiet(quiet)
    names = _resolve_methods(method, weights)
    device = resolve_device(device)
    _check_output(json_path)
    _check_output(plot_path)
    found = discover_benchmark(root, gt_dir)
    if scenes:
        wanted = [s for value in scenes for s in value.replace(",", " ").split()]
        known = {s.name for s in found}
        unknown = [s for s in wanted if s not in known]
        if unknown:
            raise click.BadParameter(
                f"unknown scene {unknown[0]!r} (found: {', '.join(sorted(known))})",
                param_hint="'--scenes'",
            )
        found = [s for s in found if s.name in wanted]
    pair_set = load_benchmark_pairs(found, limit, allow_missing)
    if not pair_set.pairs:
        raise DatasetError(
            root,
            f"no pair left to evaluate ({len(pair_set.skipped_pairs)} skipped for missing "
            "fragments)",
        )
    methods = build_methods(
        names,
        _weights_files(names, weights),
        seed=seed,
        device=device,
        fpfh_voxel_size=fpfh_voxel_size,
        icp_distance=icp_distance,
        max_points=num_samples,
    )
    config = FmrConfig(tau1=tau1, tau2=tau2, num_samples=num_samples, top_k=top_k, seed=seed)
    cache = FeatureCache(cache_dir)
    with _Display(quiet) as display:
        result = evaluate_fmr(pair_set, methods, config, cache, display)
    settings = {
        "root": str(root),
        "gt_dir": str(gt_dir) if gt_dir else None,
        "scenes_selected": list(scenes) or None,
        "limit_per_scene": limit,
        "allow_missing": allow_missing,
        "cache_dir": str(cache_dir) if cache_dir else None,
        "device": device,
        "fpfh_voxel_size": fpfh_voxel_size,
        "icp_distance": icp_distance,
    }
    report = fmr_report(result, pair_set, methods, config, settings)
    _write_outputs(report, json_path, plot_path, plot_fmr)
    if not quiet:
        notes = _method_notes(methods)
        without_info = [s.name for s in pair_set.scenes if s.gt_info is None]
        if without_info:
            notes.append(
                f"note: no gt.info for {', '.join(without_info)}: registration recall "
                "(RR) needs it (pass --gt-dir with the benchmark's ground truth)"
            )
        if pair_set.skipped_pairs:
            notes.append(
                f"note: {len(pair_set.skipped_pairs)} pair(s) skipped, "
                f"{len(pair_set.missing_fragments)} fragment(s) missing (--allow-missing)"
            )
        notes.append(
            f"{len(pair_set.pairs)} pairs in {len(pair_set.scenes)} scene(s); feature cache: "
            f"{result.cache_hits} read, {result.cache_misses} computed; "
            f"{result.seconds:.1f} s"
        )
        columns, rows = fmr_table(report)
        _print_table(f"eval-fmr {root}", columns, rows, notes)


# ================================================================== eval-pairs


@click.command(
    "eval-pairs",
    cls=EvalCommand,
    epilog="Accuracy: rotation at 5/10/45 deg, translation at 5/10/25 cm, chamfer at 1/5/10 "
    "(1e-3 m^2), mean and median of each. Exit codes: 0 done; 1 bad input; 2 usage error.",
)
@click.option(
    "--rgbd-dir",
    multiple=True,
    type=click.Path(path_type=Path),
    help="RGB-D video folder(s) with poses (TUM, 3DMatch/7-Scenes, ScanNet, Redwood layouts).",
)
@click.option(
    "--pairs-dir",
    multiple=True,
    type=click.Path(path_type=Path),
    help="Folder(s) of prepared pairs NNNN/{source.ply, target.ply, T_gt.txt}.",
)
@click.option(
    "--spacing",
    type=click.IntRange(min=1),
    default=20,
    show_default=True,
    help="Frames between the two views (every N-th frame, consecutive ones paired).",
)
@click.option(
    "--depth-scale",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Depth units per metre [default: the layout's, 5000 TUM, 1000 others].",
)
@_common_options
@handle_errors
def eval_pairs(
    rgbd_dir: tuple[Path, ...],
    pairs_dir: tuple[Path, ...],
    spacing: int,
    depth_scale: float | None,
    method: tuple[str, ...],
    weights: tuple[Path, ...],
    json_path: Path | None,
    plot_path: Path | None,
    cache_dir: Path | None,
    limit: int | None,
    fpfh_voxel_size: float,
    icp_distance: float,
    quiet: bool,
    seed: int,
    device: str,
) -> None:
    """Pairwise registration accuracy (the paper's table) on posed RGB-D video or prepared
    pairs, every method on the same pairs: rotation, translation and chamfer errors.
    """
    from byoc_cli.evaluation.cache import FeatureCache
    from byoc_cli.evaluation.methods import build_methods
    from byoc_cli.evaluation.pairs import PairsConfig, evaluate_pairs, prepared_pairs, rgbd_pairs
    from byoc_cli.evaluation.plot import plot_pairs
    from byoc_cli.evaluation.report import pairs_report, pairs_table

    quiet = _is_quiet(quiet)
    if not rgbd_dir and not pairs_dir:
        raise click.UsageError("give --rgbd-dir SEQUENCE and/or --pairs-dir FOLDER")
    names = _resolve_methods(method, weights)
    device = resolve_device(device)
    _check_output(json_path)
    _check_output(plot_path)
    pairs, sources = [], []
    if rgbd_dir:
        found, described = rgbd_pairs(rgbd_dir, spacing, limit, depth_scale)
        pairs += found
        sources += [{"kind": "rgbd", **d} for d in described]
    for folder in pairs_dir:
        found = prepared_pairs(folder, limit)
        pairs += found
        sources.append({"kind": "prepared-pairs", "root": str(folder), "pairs": len(found)})
    if not pairs:
        raise click.UsageError(
            f"no pair to evaluate: the sequences are shorter than --spacing {spacing} frames"
        )
    methods = build_methods(
        names,
        _weights_files(names, weights),
        seed=seed,
        device=device,
        fpfh_voxel_size=fpfh_voxel_size,
        icp_distance=icp_distance,
    )
    config = PairsConfig(seed=seed)
    cache = FeatureCache(cache_dir)
    with _Display(quiet) as display:
        result = evaluate_pairs(pairs, methods, config, cache, display)
    settings = {
        "rgbd_dirs": [str(p) for p in rgbd_dir],
        "pairs_dirs": [str(p) for p in pairs_dir],
        "spacing": spacing,
        "limit_per_sequence": limit,
        "depth_scale": depth_scale,
        "cache_dir": str(cache_dir) if cache_dir else None,
        "device": device,
        "fpfh_voxel_size": fpfh_voxel_size,
        "icp_distance": icp_distance,
    }
    report = pairs_report(result, methods, config, settings, sources)
    _write_outputs(report, json_path, plot_path, plot_pairs)
    if not quiet:
        motion = result.motion
        notes = _method_notes(methods)
        notes.append(
            f"{len(pairs)} pairs; ground-truth motion mean {motion['rotation_deg']['mean']:.1f}°"
            f" / {motion['translation_cm']['mean']:.1f} cm; feature cache: "
            f"{result.cache_hits} read, {result.cache_misses} computed; {result.seconds:.1f} s"
        )
        columns, rows = pairs_table(report)
        _print_table("eval-pairs", columns, rows, notes)
