"""Scans turned far apart about the vertical: `byoc register` with `--no-turns`, the default
(`auto`) and `--turns`.

The pairs of `_init_pairs.BENCH_SETS` (Kinect pairs 50 camera frames apart, RealSense tabletop
pairs) whose clouds overlap at their truth (`_init_pairs.MIN_OVERLAP`), each with its source
turned by --degrees about its own up axis (`geometry/orientation.up_axis`, through its
centroid), registered in this process by a `Registrar` with `matching.turns` off
(`--no-turns`), `auto` (the default: the turned tries where the features see the clouds at
their own voxel, as here) and on (`--turns`: the turned tries and the structure check).
Right: within 5 deg and 10 cm of the truth refined on the data (after the turn). Prints, per
turn and setting, right and passed, wrong and passed (exit 0), refused (exit 3: right or
wrong) and the median seconds per pair.

Usage:
    python benchmarks/turns.py [--degrees 0 90 180] [--pairs 28] [--settings off auto on]

Keep it bounded: `timeout 3600 bash -c 'ulimit -v 8000000; python benchmarks/turns.py'`.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from _init_pairs import MIN_OVERLAP, errors, overlap, refined_truth, rgbd_pairs

#: ``matching.turns`` of each setting
SETTINGS = {"off": False, "auto": "auto", "on": True}


def turned_pairs(limit: int):
    """``(name, source, target, truth)`` of the overlapping benchmark pairs."""
    from byoc_cli.api import Registrar

    voxels = Registrar(device="cpu")
    for pair in rgbd_pairs(limit=limit):
        src, tgt = pair.load_source(), pair.load_target()
        truth, _ = refined_truth(src, tgt, pair.T_gt, voxels.choose_voxel(src, tgt).refine_voxel)
        if overlap(src, tgt, truth) >= MIN_OVERLAP:
            yield pair.name, src, tgt, truth


def run(args) -> dict:
    """``{(degrees, setting): [(right, passed, seconds), ...]}``."""
    from byoc_cli.api import Registrar
    from byoc_cli.geometry.orientation import turn_about, up_axis
    from byoc_cli.pipeline.recipe import preset

    registrars = {}
    for setting in args.settings:  # on: as --turns (its structure check too)
        recipe = preset().changed(matching__turns=SETTINGS[setting])
        registrars[setting] = Registrar(device="cpu", recipe=recipe)
    rows = {}
    for name, src, tgt, truth in turned_pairs(args.pairs):
        centre = src.mean(axis=0)
        axis = up_axis(src - centre)
        cells = []
        for degrees in args.degrees:
            P = turn_about(axis, degrees, centre)
            source = src @ P[:3, :3].T + P[:3, 3]
            for setting, registrar in registrars.items():
                start = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    result = registrar.register(source, tgt)
                seconds = time.perf_counter() - start
                rot, trans = errors(result.T_tgt_src, truth @ np.linalg.inv(P))
                right = rot < 5 and trans < 0.10
                rows.setdefault((degrees, setting), []).append((right, result.passed, seconds))
                mark = ("R" if right else "w") + ("P" if result.passed else "-")
                cells.append(f"{degrees:g}/{setting}={mark} {result.confidence:.2f}")
        print(f"{name:36s} " + " ".join(cells), flush=True)
    return rows


def table(rows: dict) -> str:
    out = [
        "| turned by | turns | right, exit 0 | wrong, exit 0 | exit 3 (right) | s / pair |",
        "|---|---|---|---|---|---|",
    ]
    for (degrees, setting), cells in rows.items():
        right = sum(r and p for r, p, _ in cells)
        wrong = sum(p and not r for r, p, _ in cells)
        refused = sum(not p for _, p, _ in cells)
        refused_right = sum(r and not p for r, p, _ in cells)
        seconds = float(np.median([s for _, _, s in cells]))
        out.append(
            f"| {degrees:g} deg | {setting} | {right}/{len(cells)} | {wrong} | "
            f"{refused} ({refused_right}) | {seconds:.1f} |"
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--degrees", type=float, nargs="+", default=[0.0, 90.0, 180.0])
    parser.add_argument("--pairs", type=int, default=28)
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=list(SETTINGS))
    args = parser.parse_args(argv)
    print(table(run(args)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
