"""Spinning-LiDAR pairs whose rings match themselves: `byoc register` with and without the
scan-line measures (docs/voxel.md, "Scans sampled along lines").

The street pairs of benchmarks/scan_sim.py (scans in their sensor's frame: the ring pattern
is fixed to the sensor) at 16, 32, 64 and 128 rings, the second sensor 2 to 8 m ahead and
turned 0 to 30 deg, each registered in process with the defaults (`byoc_cli.register`, the
same T as `byoc register A B`) at seeds 0 .. S-1 and judged against the truth: right within
5 deg and 10 cm times the scale the auto voxel brought the pair to (its refinement voxel over
the features' reference voxel: about 0.8 m on these streets). `--without` runs the pipeline
without the measures (`SCAN_LINE_SHARE` set to 1: no cloud counts as sampled along lines, so
the voxel and the results are those of the pipeline before them).

Prints one row per pair (rings, motion, feature voxel, right of S, wrong results that exit 0,
median errors, the confidences) and the totals.

Usage: python benchmarks/scan_lines.py [--pairs all|quick] [--seeds 3] [--without]
    [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from _scan_sim_street import street_pair

#: (rings, points per scan, seed, shift m, turn deg) of each pair
PAIRS = (
    (16, 13_000, 1, 4.0, 12.0),
    (16, 13_000, 2, 7.0, 25.0),
    (16, 13_000, 3, 2.5, 0.0),
    (32, 50_000, 4, 4.0, 12.0),
    (32, 50_000, 5, 6.0, 30.0),
    (32, 50_000, 6, 3.0, 5.0),
    (64, 120_000, 7, 5.0, 18.0),
    (64, 120_000, 8, 8.0, 8.0),
    (64, 120_000, 9, 2.0, 22.0),
    (128, 250_000, 10, 4.0, 12.0),
)


def errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """Rotation (deg) and translation (m) of ``inv(T) @ T_gt``."""
    D = np.linalg.inv(T) @ T_gt
    cos = np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(D[:3, 3]))


def run_pair(spec: tuple, seeds: int, gate: float) -> dict:
    """Register one street pair at ``seeds`` seeds: its row."""
    from byoc_cli import register

    rings, points, seed, shift, yaw = spec
    src, tgt, T_gt = street_pair(points, rings, seed, shift, yaw)
    runs = []
    for s in range(seeds):
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = register(src, tgt, seed=s)
        rot, trans = errors(result.T_tgt_src, T_gt)
        choice = result.voxel_choice
        tolerance = 0.1 * choice["refine_voxel_size"] / choice["reference_voxel_size"]
        runs.append(
            {
                "seed": s,
                "rotation_deg": rot,
                "translation_m": trans,
                "right": rot < 5.0 and trans < tolerance,
                "exit": 0 if result.confidence >= gate else 3,
                "confidence": result.confidence,
                "voxel": result.voxel_size,
                "seconds": time.perf_counter() - start,
            }
        )
    return {"rings": rings, "seed": seed, "shift_m": shift, "yaw_deg": yaw, "runs": runs}


def row(pair: dict) -> str:
    """One table row of a pair."""
    runs = pair["runs"]
    right = sum(r["right"] for r in runs)
    wrong = sum(not r["right"] and r["exit"] == 0 for r in runs)
    rot = statistics.median(r["rotation_deg"] for r in runs)
    trans = statistics.median(r["translation_m"] for r in runs)
    conf = " ".join(f"{r['confidence']:.2f}" for r in runs)
    return (
        f"| {pair['rings']} | {pair['seed']} | {pair['shift_m']:g} m, {pair['yaw_deg']:g} deg "
        f"| {runs[0]['voxel']:.2f} m | {right}/{len(runs)} | {wrong} | {rot:.2f} deg "
        f"| {trans:.3f} m | {conf} |"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", choices=("all", "quick"), default="all")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--without", action="store_true", help="without the scan-line measures")
    parser.add_argument("--json", type=Path, help="write the runs here")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds must be at least 1, got {args.seeds}")
    if args.json is not None and args.json.exists():
        parser.error(f"--json {args.json}: exists; give a new file")

    import byoc_cli.pipeline.scale as scale
    from byoc_cli.pipeline.confidence import DEFAULT_MIN_CONFIDENCE

    if args.without:
        scale.SCAN_LINE_SHARE = 1.0
    specs = PAIRS if args.pairs == "all" else PAIRS[:1]
    print("| rings | seed | motion | feature voxel | right | wrong, exit 0 | median rotation "
          "error | median translation error | confidence per seed |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    pairs = []
    for spec in specs:
        pairs.append(run_pair(spec, args.seeds, DEFAULT_MIN_CONFIDENCE))
        print(row(pairs[-1]), flush=True)
    runs = [r for p in pairs for r in p["runs"]]
    right = sum(r["right"] for r in runs)
    wrong = sum(not r["right"] and r["exit"] == 0 for r in runs)
    label = "without the scan-line measures" if args.without else "with the scan-line measures"
    print(f"\n{label}: {right} of {len(runs)} right, {wrong} wrong with exit 0")
    if args.json is not None:
        args.json.write_text(json.dumps({"without": args.without, "pairs": pairs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
