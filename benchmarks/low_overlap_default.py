"""What a user gets on fragment pairs: ``byoc register-batch`` with no flags (learned features,
restarts, the FPFH fallback, the gate), scored per overlap band.

Usage::

    python benchmarks/low_overlap_default.py --fragments DEV --out OUT [--gt-dir GT]
        [--bands 0.1,0.3,1] [--tag NAME] [--byoc "byoc"] [--byoc-args="..."]

``DEV`` is a fragment benchmark in the 3DMatch layout (``byoc make-fragments ... --min-overlap
0.1``, or the 3DMatch sample with ``--gt-dir ../shared/data/3dmatch/benchmarks/3DLoMatch``).
Every pair of its ``gt.log`` (source ``j``, target ``i``) goes into one list for one
``register-batch`` process (``OUT/pairs-TAG.txt``, summary ``OUT/summary-TAG.jsonl``; a summary
already there is scored again without registering). Per band ``(low, high]`` of
``gt_overlap.log`` (all pairs in one band without one):

* RR: the official registration recall (RMSE from ``gt.info`` at most 0.2 m) of the returned
  transforms, exit code aside, over the pairs ``j - i > 1``;
* exit 0 right / wrong, refused (exit 3): every pair, right by the RR criterion and a rotation
  error under 5 deg (issue 35's count of wrong results with exit 0);
* right but refused.

``--byoc`` is the command that runs ``byoc`` (a wrapper of it, for an experiment) and
``--byoc-args`` options added to ``register-batch``.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import subprocess
import sys
from itertools import pairwise
from pathlib import Path

import numpy as np

RR_RMSE = 0.2
MAX_ROT_DEG = 5.0


def _pairs(root: Path, gt_dir: Path | None) -> list:
    from byoc_cli.evaluation.benchmark import load_benchmark_pairs
    from byoc_cli.io.threedmatch import discover_benchmark

    return load_benchmark_pairs(discover_benchmark(root, gt_dir)).pairs


def _bands(text: str | None) -> list[tuple[float, float]]:
    if not text:
        return [(-math.inf, math.inf)]
    edges = [float(x) for x in text.split(",")]
    return list(pairwise(edges))


def register(pairs: list, out: Path, tag: str, byoc: str, extra: str) -> Path:
    """Run one ``register-batch`` over ``pairs``; the summary's path."""
    summary = out / f"summary-{tag}.jsonl"
    if summary.exists():
        return summary
    lines = [
        f"{p.source.resolve()} {p.target.resolve()} "
        f"{(out / f'T-{tag}' / f'{p.scene}_{p.i}_{p.j}.txt').resolve()}"
        for p in pairs
    ]
    (out / f"T-{tag}").mkdir(parents=True, exist_ok=True)
    listed = out / f"pairs-{tag}.txt"
    listed.write_text("\n".join(lines) + "\n")
    command = [*shlex.split(byoc), "register-batch", str(listed), "--summary", str(summary), "-q"]
    run = subprocess.run([*command, *shlex.split(extra)], check=False)
    if run.returncode not in (0, 3):
        summary.unlink(missing_ok=True)
        raise SystemExit(f"{shlex.join(command)} exited with {run.returncode}")
    return summary


def score(pairs: list, summary: Path) -> list[dict]:
    """One record per pair: band key, RMSE, rotation error, exit-0 flag."""
    from byoc_cli.evaluation.metrics import pose_errors, registration_rmse

    by_source = {(str(p.source.resolve()), str(p.target.resolve())): p for p in pairs}
    records = []
    for line in summary.read_text().splitlines():
        r = json.loads(line)
        p = by_source[(str(Path(r["source"]).resolve()), str(Path(r["target"]).resolve()))]
        rmse, rot = math.inf, math.inf
        if r.get("T_tgt_src") is not None:
            T = np.array(r["T_tgt_src"])
            rot = pose_errors(T, p.T_gt)[0]
            if p.info is not None:
                rmse = registration_rmse(T, p.T_gt, p.info)
        records.append(
            {
                "pair": f"{p.scene} {p.i} {p.j}",
                "overlap": p.overlap,
                # the recall's pairs: j - i > 1 with an information matrix (one 3DLoMatch
                # record is all zeros); a pair without a transform counts as not registered
                "in_rr": p.j - p.i > 1 and p.info is not None and float(p.info[0][0]) > 0,
                "rr": rmse <= RR_RMSE,
                "right": rmse <= RR_RMSE and rot < MAX_ROT_DEG,
                "passed": bool(r.get("passed")) and r.get("status") != "error",
                "confidence": r.get("confidence"),
                "rot": rot,
                "rmse": rmse,
            }
        )
    return records


def table(records: list[dict], bands: list[tuple[float, float]]) -> list[str]:
    rows = [
        "| band | pairs | RR % (in RR) | exit 0 right | exit 0 wrong | refused | right, refused |",
        "|---|---|---|---|---|---|---|",
    ]
    for low, high in bands:
        part = [r for r in records if r["overlap"] is None or low < r["overlap"] <= high]
        if not part:
            continue
        rr = [r for r in part if r["in_rr"]]
        rate = 100 * sum(r["rr"] for r in rr) / len(rr) if rr else float("nan")
        ok0 = sum(r["passed"] and r["right"] for r in part)
        bad0 = sum(r["passed"] and not r["right"] for r in part)
        refused = sum(not r["passed"] for r in part)
        right_refused = sum(not r["passed"] and r["right"] for r in part)
        name = "all" if math.isinf(low) else f"{low:g}-{high:g}"
        rows.append(
            f"| {name} | {len(part)} | {rate:.1f} ({len(rr)}) | {ok0} | {bad0} | {refused} | "
            f"{right_refused} |"
        )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fragments", type=Path, required=True)
    parser.add_argument("--gt-dir", type=Path, default=None)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--bands", default=None, help="band edges, e.g. 0.1,0.3,1")
    parser.add_argument("--tag", default="default")
    parser.add_argument("--byoc", default="byoc", help="the command that runs byoc")
    parser.add_argument("--byoc-args", default="", help="options added to register-batch")
    args = parser.parse_args()
    from byoc_cli.errors import InputError

    try:
        bands = _bands(args.bands)
    except ValueError:
        parser.error(f"--bands {args.bands}: expected numbers separated by commas")
    try:
        pairs = _pairs(args.fragments, args.gt_dir)
    except InputError as err:
        parser.error(str(err))
    args.out.mkdir(parents=True, exist_ok=True)
    summary = register(pairs, args.out, args.tag, args.byoc, args.byoc_args)
    records = score(pairs, summary)
    (args.out / f"scores-{args.tag}.json").write_text(json.dumps(records, indent=1))
    print("\n".join(table(records, bands)))
    wrong = [r for r in records if r["passed"] and not r["right"]]
    for r in wrong:
        print(
            f"wrong, exit 0: {r['pair']} overlap {r['overlap']} confidence {r['confidence']:.2f} "
            f"rot {r['rot']:.1f} deg RMSE {r['rmse']:.2f} m",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
