"""Robust estimators on the low- and high-overlap development pairs: RANSAC, randomized
Procrustes and second-order spatial compatibility (``sc2``), with learned and FPFH features.

Usage::

    python benchmarks/low_overlap_estimators.py --fragments DEV --out eval/ \
        [--cache-dir features/] [--features byoc fpfh] [--estimators ransac procrustes sc2] \
        [--sets dev-low dev-high 3DLoMatch-sample 3DMatch-sample] [--full] [--limit N] \
        [--table-only]

``DEV`` and the pair sets are those of ``benchmarks/low_overlap.py`` (the development fragments
of docs/low-overlap.md split at 30 % overlap, and the 3DMatch sample with the official ground
truth). Each feature kind is ``byoc eval-fmr``'s method of that name (``byoc``: the shipped
weights with ``byoc register``'s recipe; ``fpfh``: ``--method fpfh-ransac``, the ``byoc register
--features fpfh`` recipe), on the same seeded 5000 points per fragment and the same pair seeds,
with only the estimator changed. Features are computed once per fragment (``--cache-dir``
shares ``low_overlap.py``'s cache).

By default the estimator is measured alone: matching and the robust fit, no refinement
(``refine=None``; the fit's own seconds are ``timings["fit"]``). ``--full`` adds the feature
kind's whole recipe (for ``byoc`` the multiscale refinement on the full-resolution fragments
and its restarts; ``fpfh`` has none, so its full rows equal the coarse ones and are not run).

Scored per pair set: registration recall (the official RMSE from ``gt.info`` at most 0.2 m,
pairs ``j - i > 1``; their count in brackets), rotation accuracy (error < 5 deg) and translation
accuracy (< 10 cm) over every pair of the set, the median seconds of the fit and the mean
seconds of the registration (matching, fit, refinement, verdict; features excluded). Then
each estimator's ratios against RANSAC with the same features: pairs registered, time.

One JSON of per-pair records per feature kind, estimator, set and mode goes to ``--out``; a
JSON already there is reused, so an interrupted sweep resumes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import low_overlap

ESTIMATORS = ("ransac", "procrustes", "sc2")
#: feature kind -> eval-fmr method
FEATURES = {"byoc": "byoc", "fpfh": "fpfh-ransac"}
SETS = low_overlap.SETS
RMSE = 0.2
ROTATION_DEG = 5.0
TRANSLATION_M = 0.10


def _pairs(name: str, fragments: Path, limit: int | None):
    """The pairs of one set (:func:`low_overlap._set`)."""
    from byoc_cli.evaluation.bands import parse_overlap_bands, split_by_band
    from byoc_cli.evaluation.fmr import load_benchmark_pairs
    from byoc_cli.io.threedmatch import discover_benchmark

    root, gt_dir, bands = low_overlap._set(name, fragments)
    pairs = load_benchmark_pairs(discover_benchmark(root, gt_dir)).pairs
    if bands:
        members, _ = split_by_band([p.overlap for p in pairs], parse_overlap_bands(bands))
        pairs = [pairs[k] for k in sorted(k for m in members for k in m)]
    return pairs[:limit] if limit else pairs


class _Fragments:
    """Points and features of the fragments, each computed once (features through the
    on-disk cache)."""

    def __init__(self, cache_dir: Path | None) -> None:
        from byoc_cli.evaluation.cache import FeatureCache

        self.cache = FeatureCache(cache_dir)
        self.points: dict[Path, object] = {}
        self.feats: dict[tuple[str, Path], object] = {}

    def cloud(self, path: Path):
        import torch

        from byoc_cli.io.pointcloud import read_point_cloud

        if path not in self.points:
            self.points[path] = torch.from_numpy(read_point_cloud(path).points)
        return self.points[path]

    def features(self, spec, path: Path):
        from byoc_cli.evaluation.cache import file_identity

        key = (spec.key, path)
        if key not in self.feats:
            self.feats[key] = self.cache.get(
                spec.identity,
                file_identity(path),
                lambda: spec.extractor(self.cloud(path), label=str(path)),
            )
        return self.feats[key]


def _run(method, estimator: str, full: bool, pairs, fragments: _Fragments) -> list[dict]:
    """Per-pair records of one feature kind's method with ``estimator``."""
    import torch

    from byoc_cli.errors import RegistrationError
    from byoc_cli.evaluation.fmr_protocol import FmrConfig, pair_seed
    from byoc_cli.evaluation.metrics import pose_errors, registration_rmse
    from byoc_cli.pipeline.register import estimate_transform

    config = dataclasses.replace(method.config, estimator=estimator)
    if not full:
        config = dataclasses.replace(config, refine=None)
    records = []
    start_all = time.perf_counter()
    for n, pair in enumerate(pairs, 1):
        feats = (
            fragments.features(method.features, pair.source),
            fragments.features(method.features, pair.target),
        )
        clouds = (fragments.cloud(pair.source), fragments.cloud(pair.target))
        seed = pair_seed(FmrConfig().seed, pair.scene, pair.i, pair.j)
        start = time.perf_counter()
        try:
            result = estimate_transform(
                *feats,
                dataclasses.replace(config, seed=seed),
                method.features.voxel_size,
                clouds if config.refine else None,
            )
            T, timings, failed = result.T_tgt_src.double(), result.timings, None
        except RegistrationError as exc:
            T, timings, failed = torch.eye(4, dtype=torch.float64), {}, str(exc)
        seconds = time.perf_counter() - start
        T_gt = torch.from_numpy(pair.T_gt)
        rot, trans = pose_errors(T, T_gt)
        rmse = registration_rmse(T, T_gt, pair.info) if pair.info is not None else None
        records.append(
            {
                "scene": pair.scene,
                "i": pair.i,
                "j": pair.j,
                "overlap": pair.overlap,
                "official": pair.j - pair.i > 1 and rmse is not None,
                "rotation_error_deg": rot,
                "translation_error_m": trans,
                "rmse_m": rmse,
                "failed": failed,
                "fit_seconds": timings.get("fit"),
                "seconds": seconds,
            }
        )
        if n % 10 == 0 or n == len(pairs):
            print(
                f"  {n}/{len(pairs)} pairs, {time.perf_counter() - start_all:.0f} s",
                file=sys.stderr,
                flush=True,
            )
    return records


def summarize(records: list[dict]) -> dict:
    """Recall, accuracies and seconds of one run's records."""
    official = [r for r in records if r["official"]]
    registered = [r for r in official if r["rmse_m"] <= RMSE]  # NaN (degenerate info): not
    fits = [r["fit_seconds"] for r in records if r["fit_seconds"] is not None]
    n = max(len(records), 1)
    return {
        "pairs": len(records),
        "official": len(official),
        "registered": len(registered),
        "rr": 100.0 * len(registered) / len(official) if official else float("nan"),
        "rot": 100.0 * sum(r["rotation_error_deg"] < ROTATION_DEG for r in records) / n,
        "trans": 100.0 * sum(r["translation_error_m"] < TRANSLATION_M for r in records) / n,
        "fit_s": statistics.median(fits) if fits else float("nan"),
        "s": statistics.fmean(r["seconds"] for r in records) if records else float("nan"),
        "keys": {(r["scene"], r["i"], r["j"]) for r in registered},
    }


def _table(rows: list[tuple[str, str, str, str, dict]]) -> None:
    """Print the Markdown table and the ratios against RANSAC."""
    print(
        "| set | features | estimator | mode | RR % (registered / pairs) | rot < 5 deg % | "
        "trans < 10 cm % | fit s (median) | s / pair |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, kind, estimator, mode, s in rows:
        print(
            f"| {name} | {kind} | {estimator} | {mode} | {s['rr']:.1f} "
            f"({s['registered']} / {s['official']}) | {s['rot']:.1f} | {s['trans']:.1f} | "
            f"{s['fit_s']:.3f} | {s['s']:.2f} |"
        )
    base = {(n, k, m): s for n, k, e, m, s in rows if e == "ransac"}
    lines = []
    for name, kind, estimator, mode, s in rows:
        ref = base.get((name, kind, mode))
        if estimator == "ransac" or ref is None:
            continue
        gained = len(s["keys"] - ref["keys"])
        lost = len(ref["keys"] - s["keys"])
        ratio = s["fit_s"] / ref["fit_s"] if ref["fit_s"] > 0 else float("nan")
        lines.append(
            f"{name} {kind} {mode}: {estimator} registers {s['registered']} against RANSAC's "
            f"{ref['registered']} (+{gained} / -{lost} pairs), fit time x{ratio:.2f}, "
            f"pair time x{s['s'] / ref['s']:.2f}"
        )
    if lines:
        print("\n" + "\n".join(lines))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fragments", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cache-dir", type=Path, default=None)
    parser.add_argument("--features", nargs="+", default=list(FEATURES), choices=FEATURES)
    parser.add_argument("--estimators", nargs="+", default=list(ESTIMATORS), choices=ESTIMATORS)
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS)
    parser.add_argument("--full", action="store_true", help="also the recipe's refinement")
    parser.add_argument("--limit", type=int, default=None, help="first N pairs of each set")
    parser.add_argument("--table-only", action="store_true")
    args = parser.parse_args()
    if not args.fragments.is_dir():
        parser.error(f"--fragments {args.fragments}: no such folder")
    args.out.mkdir(parents=True, exist_ok=True)

    from byoc_cli.evaluation.methods import build_methods
    from byoc_cli.pipeline.default_weights import default_weights_path

    methods = None
    fragments = _Fragments(args.cache_dir)
    modes = ["coarse", "full"] if args.full else ["coarse"]
    rows = []
    for name in args.sets:
        pairs = None
        for kind in args.features:
            for mode in modes:
                if mode == "full" and kind == "fpfh":
                    continue  # the fpfh recipe has no refinement: its full run is the coarse one
                for estimator in args.estimators:
                    limit = f"-limit{args.limit}" if args.limit else ""
                    out = args.out / f"{name}-{kind}-{estimator}-{mode}{limit}.json"
                    if not out.exists():
                        if args.table_only:
                            continue
                        if methods is None:
                            methods = dict(
                                zip(
                                    FEATURES,
                                    build_methods(
                                        list(FEATURES.values()),
                                        [default_weights_path()],
                                        max_points=5000,
                                    ),
                                    strict=True,
                                )
                            )
                        pairs = (
                            pairs if pairs is not None else _pairs(name, args.fragments, args.limit)
                        )
                        print(f"running {kind} {estimator} {mode} on {name}", file=sys.stderr)
                        records = _run(methods[kind], estimator, mode == "full", pairs, fragments)
                        out.write_text(json.dumps(records, indent=1) + "\n")
                    records = json.loads(out.read_text())
                    rows.append((name, kind, estimator, mode, summarize(records)))
    _table(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
