"""``byoc eval-fmr`` and ``byoc eval-pairs``: methods side by side on the same pairs.

Tables and progress go to stderr; ``--json`` writes every figure (``-`` is stdout, which is
otherwise left empty); ``--plot`` writes a PNG of accuracy against threshold. The options
both share are in :mod:`byoc_cli.cli.eval_options`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.display import EvalDisplay, print_table
from byoc_cli.cli.errors import handle_errors
from byoc_cli.cli.eval_options import (
    DEFAULT_METHODS,
    EvalCommand,
    EvalRun,
    eval_options,
    expand_method_args,
    method_notes,
)
from byoc_cli.cli.options import DEPTH_SCALE, LENGTH, finite_float, float_option, int_option

__all__ = ["DEFAULT_METHODS", "eval_fmr", "eval_pairs", "expand_method_args"]


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
@int_option(
    "--num-samples",
    default=5000,
    help="Points sampled per fragment for FMR and registration (0 = all).",
)
@float_option("--tau1", type=LENGTH, default=0.10, help="FMR inlier distance (m).")
@float_option("--tau2", type=finite_float(0, 1), default=0.05, help="FMR inlier-ratio threshold.")
@int_option(
    "--top-k",
    min=1,
    default=200,
    help="Ratio-test correspondences per direction for the 'corr' FMR.",
)
@click.option(
    "--overlap-bands",
    metavar="EDGES",
    default=None,
    help="Report the pairs by overlap band, side by side: '0.1,0.3,1' gives 3DLoMatch's "
    "(10-30 %] and 3DMatch's (30-100 %] columns per method in one run. Overlaps come from "
    "gt_overlap.log (byoc make-fragments writes it); pairs in no band are left out.",
)
@eval_options
@handle_errors
def eval_fmr(
    root: Path,
    gt_dir: Path | None,
    scenes: tuple[str, ...],
    allow_missing: bool,
    **common: Any,
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
    from byoc_cli.evaluation.plot import plot_fmr
    from byoc_cli.evaluation.report import fmr_report, fmr_table
    from byoc_cli.io.threedmatch import discover_benchmark

    protocol = {name: common.pop(name) for name in ("num_samples", "tau1", "tau2", "top_k")}
    num_samples = protocol["num_samples"]
    bands = _parse_bands(common.pop("overlap_bands"))
    run = EvalRun(**common)
    run.start(input_dirs=(root, gt_dir))
    found = _select_scenes(discover_benchmark(root, gt_dir), scenes)
    pair_set = load_benchmark_pairs(found, run.limit, allow_missing)
    num_outside = 0
    if bands:
        pair_set, num_outside = _pairs_in_bands(pair_set, bands)
    if not pair_set.pairs:
        raise DatasetError(
            root,
            f"no pair left to evaluate ({len(pair_set.skipped_pairs)} skipped for missing "
            "fragments)",
        )
    methods = run.build_methods(max_points=num_samples)
    config = FmrConfig(**protocol, seed=run.seed)
    with EvalDisplay(run.quiet) as display:
        result = evaluate_fmr(pair_set, methods, config, FeatureCache(run.cache_dir), display)
    settings = {
        "root": str(root),
        "gt_dir": str(gt_dir) if gt_dir else None,
        "scenes_selected": list(scenes) or None,
        "limit_per_scene": run.limit,
        "allow_missing": allow_missing,
        "overlap_bands": [list(b) for b in bands] or None,
        **run.settings(),
    }
    report = fmr_report(result, pair_set, methods, config, settings, bands, num_outside)
    run.write(report, plot_fmr)
    if not run.quiet:
        columns, rows = fmr_table(report)
        notes = _fmr_notes(methods, pair_set, result)
        if bands:
            notes.insert(
                -1,
                "overlap bands from gt_overlap.log: "
                + ", ".join(
                    f"{b.label} {n['num_pairs']} pairs"
                    for b, n in zip(bands, report["bands"], strict=True)
                )
                + f"; {num_outside} pair(s) in no band left out",
            )
        print_table(f"eval-fmr {root}", columns, rows, notes)


def _parse_bands(text: str | None) -> list:
    """``--overlap-bands`` as :class:`~byoc_cli.evaluation.bands.OverlapBand` s (none: [])."""
    from byoc_cli.evaluation.bands import parse_overlap_bands

    if text is None:
        return []
    try:
        return parse_overlap_bands(text)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--overlap-bands'") from None


def _pairs_in_bands(pair_set, bands) -> tuple[Any, int]:
    """``pair_set`` reduced to the pairs of some band, and how many were left out.

    Raises:
        DatasetError: a pair has no overlap (its scene has no gt_overlap.log, or the file
            lacks the pair).
    """
    from byoc_cli.errors import DatasetError
    from byoc_cli.evaluation.bands import split_by_band

    for pair in pair_set.pairs:
        if pair.overlap is None:
            scene = next(s for s in pair_set.scenes if s.name == pair.scene)
            where = scene.gt_overlap or scene.gt_log.parent
            what = "lacks pair" if scene.gt_overlap else "no gt_overlap.log for pair"
            raise DatasetError(
                where,
                f"{what} {pair.i} {pair.j}: --overlap-bands needs every pair's overlap "
                "(pass --gt-dir with the benchmark's ground truth, or drop --overlap-bands)",
            )
    members, outside = split_by_band([p.overlap for p in pair_set.pairs], bands)
    keep = sorted(k for band in members for k in band)
    return pair_set._replace(pairs=[pair_set.pairs[k] for k in keep]), len(outside)


def _select_scenes(found: list, scenes: tuple[str, ...]) -> list:
    """The scenes named by ``--scenes`` (all when none is named)."""
    if not scenes:
        return found
    wanted = [s for value in scenes for s in value.replace(",", " ").split()]
    known = {s.name for s in found}
    unknown = [s for s in wanted if s not in known]
    if unknown:
        raise click.BadParameter(
            f"unknown scene {unknown[0]!r} (found: {', '.join(sorted(known))})",
            param_hint="'--scenes'",
        )
    return [s for s in found if s.name in wanted]


def _fmr_notes(methods, pair_set, result) -> list[str]:
    notes = method_notes(methods)
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
    return notes


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
@int_option(
    "--spacing",
    min=1,
    default=20,
    help="Frames between the two views (every N-th frame, consecutive ones paired).",
)
@float_option(
    "--depth-scale",
    type=DEPTH_SCALE,
    help="Depth units per metre [default: the layout's, 5000 TUM, 1000 others].",
)
@eval_options
@handle_errors
def eval_pairs(
    rgbd_dir: tuple[Path, ...],
    pairs_dir: tuple[Path, ...],
    spacing: int,
    depth_scale: float | None,
    **common: Any,
) -> None:
    """Pairwise registration accuracy (the paper's table) on posed RGB-D video or prepared
    pairs, every method on the same pairs: rotation, translation and chamfer errors.
    """
    from byoc_cli.evaluation.cache import FeatureCache
    from byoc_cli.evaluation.pairs import PairsConfig, evaluate_pairs, prepared_pairs, rgbd_pairs
    from byoc_cli.evaluation.plot import plot_pairs
    from byoc_cli.evaluation.report import pairs_report, pairs_table

    if not rgbd_dir and not pairs_dir:
        raise click.UsageError("give --rgbd-dir SEQUENCE and/or --pairs-dir FOLDER")
    run = EvalRun(**common)
    run.start(input_dirs=(*rgbd_dir, *pairs_dir))
    pairs, sources = [], []
    if rgbd_dir:
        found, described = rgbd_pairs(rgbd_dir, spacing, run.limit, depth_scale)
        pairs += found
        sources += [{"kind": "rgbd", **d} for d in described]
    for folder in pairs_dir:
        found = prepared_pairs(folder, run.limit)
        pairs += found
        sources.append({"kind": "prepared-pairs", "root": str(folder), "pairs": len(found)})
    if not pairs:
        raise click.UsageError(
            f"no pair to evaluate: the sequences are shorter than --spacing {spacing} frames"
        )
    methods = run.build_methods()
    config = PairsConfig(seed=run.seed)
    with EvalDisplay(run.quiet) as display:
        result = evaluate_pairs(pairs, methods, config, FeatureCache(run.cache_dir), display)
    settings = {
        "rgbd_dirs": [str(p) for p in rgbd_dir],
        "pairs_dirs": [str(p) for p in pairs_dir],
        "spacing": spacing,
        "limit_per_sequence": run.limit,
        "depth_scale": depth_scale,
        **run.settings(),
    }
    report = pairs_report(result, methods, config, settings, sources)
    run.write(report, plot_pairs)
    if not run.quiet:
        motion = result.motion
        notes = method_notes(methods)
        notes.append(
            f"{len(pairs)} pairs; ground-truth motion mean {motion['rotation_deg']['mean']:.1f}°"
            f" / {motion['translation_cm']['mean']:.1f} cm; feature cache: "
            f"{result.cache_hits} read, {result.cache_misses} computed; {result.seconds:.1f} s"
        )
        columns, rows = pairs_table(report)
        print_table("eval-pairs", columns, rows, notes)
