"""Low-overlap levers that need no training, on the development fragments and the 3DMatch sample.

Usage::

    python benchmarks/low_overlap.py --fragments DEV --out eval/ [--cache-dir features/]
        [--levers shipped fpfh mutual ...] [--sets dev-low dev-high ...] [--coarse]
        [--table-only]

``DEV`` is a fragment benchmark whose gt.log holds every pair above 10 % overlap with its
``gt_overlap.log`` (``byoc make-fragments ... --min-overlap 0.1``, one folder per scene; several
benchmarks can be joined by linking their scene folders into one). Every lever is the shipped
weights with ``byoc register``'s defaults for learned features and ONE setting changed (the
``fpfh`` row is ``--method fpfh-ransac``, the ``byoc register --features fpfh`` pipeline), run
through ``byoc eval-fmr``'s evaluation (the same seeded 5000 points per fragment, the same
protocols) on:

* ``dev-low`` and ``dev-high``: the development fragments whose overlap is 10-30 % (3DLoMatch's
  band) and above 30 % (3DMatch's), as ``byoc eval-fmr DEV --overlap-bands 0.1,0.3`` and
  ``--overlap-bands 0.3,1``;
* ``3DLoMatch-sample`` (5 pairs, 10-30 %) and ``3DMatch-sample`` (3 pairs above 30 %), with the
  official ground truth of ``../shared/data/3dmatch/benchmarks``.

``--sets`` runs some of them (a lever that does not raise ``dev-low`` needs no other run).
``--coarse`` screens the levers without the refinement (``--refine none`` for every row, the
``shipped`` one included; JSON names end in ``-coarse``): the multiscale refinement on the
full-resolution fragments takes most of a pair's time (65 of 85 s on a desk pair of 75k and
354k points) and is the same for every lever; a lever that does not raise the coarse recall is
not run in full.

One JSON per lever and pair set goes to ``--out`` (the ``eval-fmr --json`` report); a JSON
already there is reused, so an interrupted sweep resumes. Printed: a Markdown table, one row per
lever: official registration recall (RMSE <= 0.2 m, pairs ``j - i > 1``) and success rate
(rotation < 15 deg, translation < 30 cm) per set, and seconds per pair.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
SAMPLE = DATA / "3dmatch" / "sample"
GT = DATA / "3dmatch" / "benchmarks"

#: lever name -> (method, RegisterConfig fields changed from the byoc defaults)
LEVERS: dict[str, tuple[str, dict]] = {
    "shipped": ("byoc", {}),
    "fpfh": ("fpfh-ransac", {}),
    "mutual": ("byoc", {"mutual": True}),
    "top-1000": ("byoc", {"num_correspondences": 1000}),
    "top-5000": ("byoc", {"num_correspondences": 5000}),
    "ransac-1M": ("byoc", {"ransac_iterations": 1_000_000}),
    "inlier-1.5v": ("byoc", {"inlier_factor": 1.5}),
    "inlier-3v": ("byoc", {"inlier_factor": 3.0}),
    "inlier-4v": ("byoc", {"inlier_factor": 4.0}),
    "points-10k": ("byoc", {"max_points": 10_000}),
    "points-20k": ("byoc", {"max_points": 20_000}),
    "mutual+ransac-1M": ("byoc", {"mutual": True, "ransac_iterations": 1_000_000}),
    "points-10k+ransac-1M": ("byoc", {"max_points": 10_000, "ransac_iterations": 1_000_000}),
}
SETS = ("dev-low", "dev-high", "3DLoMatch-sample", "3DMatch-sample")


def _set(name: str, fragments: Path) -> tuple[Path, Path | None, str | None]:
    """``(root, gt_dir, bands)`` of a pair set."""
    return {
        "dev-low": (fragments, None, "0.1,0.3"),
        "dev-high": (fragments, None, "0.3,1"),
        "3DLoMatch-sample": (SAMPLE / "3DLoMatch", GT / "3DLoMatch", None),
        "3DMatch-sample": (SAMPLE / "3DMatch", GT / "3DMatch", None),
    }[name]


def _slug(text: str) -> str:
    return text.replace(" ", "_").replace("+", "_")


class _Log:
    """Progress of the evaluation on stderr: a line every 10 pairs, with the time."""

    def __init__(self, label: str) -> None:
        self.label = label
        self.done: dict[str, int] = {}
        self.total: dict[str, int] = {}
        self.t0 = time.perf_counter()

    def start(self, task: str, total: int) -> None:
        self.done[task], self.total[task] = 0, total

    def advance(self, task: str, steps: int = 1) -> None:
        self.done[task] += steps
        if task == "pairs" and (self.done[task] % 10 == 0 or self.done[task] == self.total[task]):
            print(
                f"  {self.label}: {self.done[task]}/{self.total[task]} pairs, "
                f"{time.perf_counter() - self.t0:.0f} s",
                file=sys.stderr,
                flush=True,
            )


def _evaluate(
    lever: str,
    root: Path,
    gt_dir: Path | None,
    bands: str | None,
    cache: Path | None,
    coarse: bool,
    weights_path: Path | None = None,
):
    """The eval-fmr report of one lever on one pair set (``weights_path``: the learned
    levers' weights; None: the shipped ones)."""
    from byoc_cli.evaluation.bands import parse_overlap_bands, split_by_band
    from byoc_cli.evaluation.cache import FeatureCache
    from byoc_cli.evaluation.fmr import FmrConfig, evaluate_fmr, load_benchmark_pairs
    from byoc_cli.evaluation.methods import build_methods
    from byoc_cli.evaluation.report import fmr_report
    from byoc_cli.io.threedmatch import discover_benchmark
    from byoc_cli.pipeline.default_weights import default_weights_path

    method, changes = LEVERS[lever]
    if coarse:
        changes = {**changes, "refine": None}
    weights = [weights_path or default_weights_path()] if method == "byoc" else []
    methods = build_methods([method], weights, max_points=5000)
    methods[0].config = dataclasses.replace(methods[0].config, **changes)
    methods[0].name = lever
    pair_set = load_benchmark_pairs(discover_benchmark(root, gt_dir))
    band_list = parse_overlap_bands(bands) if bands else []
    outside = 0
    if band_list:
        members, rest = split_by_band([p.overlap for p in pair_set.pairs], band_list)
        keep = sorted(k for m in members for k in m)
        pair_set = pair_set._replace(pairs=[pair_set.pairs[k] for k in keep])
        outside = len(rest)
    config = FmrConfig()
    log = _Log(f"{lever} on {root.name}")
    result = evaluate_fmr(pair_set, methods, config, FeatureCache(cache), log)
    settings = {"root": str(root), "gt_dir": str(gt_dir) if gt_dir else None, "lever": lever}
    settings["changes"] = changes
    return fmr_report(result, pair_set, methods, config, settings, band_list, outside)


def _cell(summary: dict) -> str:
    rr = summary.get("registration_recall")
    succ = summary.get("success_rate")
    rr_text = "-" if not rr else f"{100 * rr['pooled']:.1f} ({rr['num_pairs']})"
    succ_text = "-" if not succ else f"{100 * succ['pooled']:.1f}"
    return f"{rr_text} / {succ_text}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fragments", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cache-dir", type=Path, default=None)
    parser.add_argument("--levers", nargs="+", default=list(LEVERS))
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS)
    parser.add_argument("--coarse", action="store_true")
    parser.add_argument("--table-only", action="store_true")
    parser.add_argument(
        "--weights",
        type=Path,
        default=None,
        help="weights of the learned levers (default: the shipped ones); their reports are "
        "named after the file",
    )
    args = parser.parse_args()
    unknown = [lever for lever in args.levers if lever not in LEVERS]
    if unknown:
        parser.error(f"unknown lever {unknown[0]!r} (known: {', '.join(LEVERS)})")
    if not args.fragments.is_dir():
        parser.error(f"--fragments {args.fragments}: no such folder")
    args.out.mkdir(parents=True, exist_ok=True)
    header = ["lever", *SETS, "s / pair (dev-low)"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for lever in args.levers:
        reports = {}
        for name in SETS:
            root, gt_dir, bands = _set(name, args.fragments)
            suffix = "-coarse" if args.coarse else ""
            tag = f"{args.weights.stem}-" if args.weights and LEVERS[lever][0] == "byoc" else ""
            out = args.out / f"{tag}{_slug(lever)}-{name}{suffix}.json"
            if not out.exists():
                if args.table_only or name not in args.sets:
                    continue
                print(f"running {lever} on {name}", file=sys.stderr, flush=True)
                report = _evaluate(
                    lever, root, gt_dir, bands, args.cache_dir, args.coarse, args.weights
                )
                out.write_text(json.dumps(report, indent=1) + "\n")
            reports[name] = json.loads(out.read_text())
        cells = [_cell(reports[n]["results"][lever]) if n in reports else "-" for n in SETS]
        low = reports.get("dev-low")
        cells.append(f"{low['results'][lever]['seconds_per_pair']:.2f}" if low else "-")
        label = (
            f"{args.weights.stem}: {lever}"
            if args.weights and LEVERS[lever][0] == "byoc"
            else lever
        )
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
