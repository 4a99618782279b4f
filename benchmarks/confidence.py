"""The development set of the confidence gate: register many pairs, keep every cue, fit.

`collect` registers every pair of the development set with the CLI's defaults (the Python API,
`voxel_size="auto"`), judges each result against the ground truth and appends one JSON line
per pair (its cues, its errors, right or wrong) to OUT.jsonl; a rerun skips the pairs already
there. The set, made at run time from ../shared/data:

* posed RGB-D pairs at many frame distances, wide ones included (most of the failures):
  tum_fr1_desk_full, tum_fr3_cabinet, realsense_tabletop, tum_fr1_rpy, tum_fr1_desk;
* every pair among the five fragments of the 3DMatch sample with ground truth (3DMatch and
  3DLoMatch records); the two pairs in neither file overlap by less than 10 %: negatives;
* the demo pair and the sample's 3DMatch pairs scaled by 0.01 and 100, thinned to 1/2 and 1/4
  (both clouds, or the source alone), with noise of 0.25 and 0.5 voxel;
* pairs that cannot be right: uniform noise onto a cloud, noise onto noise, a plane onto a
  plane, depth frames of two different rooms.

Right means within 5 deg and 10 cm (times the scale of a scaled copy).

`fit` fits the probability that a result is right (logistic regression on the cues,
:mod:`byoc_cli.pipeline.confidence`), by sequence-grouped cross-validation prints precision
and recall of exit 0 at each threshold and a reliability diagram, and prints the coefficients
and the threshold for at least 99 % precision.

Usage:
    python benchmarks/confidence.py collect --out dev.jsonl [--part I/N]
    python benchmarks/confidence.py collect --out coarse.jsonl --refine none \
        --truth-from dev.jsonl
    python benchmarks/confidence.py fit dev.jsonl [more.jsonl ...] [--checked check.jsonl]
    python benchmarks/confidence.py check-truth dev.jsonl [more.jsonl ...] --out check.jsonl \
        [--part I/N]
    python benchmarks/confidence.py agreement dev.jsonl ... --coarse coarse.jsonl ... \
        [--checked check.jsonl ...]
    python benchmarks/confidence.py floor --out floor.jsonl [--part I/N]
    python benchmarks/confidence.py floor-table floor.jsonl [more.jsonl ...]

`check-truth` refines every pair's ground truth a second time, with Open3D's multiscale
point-to-plane ICP instead of byoc's (the first refinement is the collection's
``T_gt_refined``). `fit --checked` then also scores the gate on the pairs whose truth the data
determine: the two refinements agree within a quarter of the thresholds. Where they do not
(the clouds' planes leave the pose free to slide, for one), right and wrong at 5 deg and
10 cm are not known, and those pairs are left out of that second table (not of the fit).

`agreement` counts, per group, the learned results that agree with FPFH's unrefined result of
the same pair (from a `collect --refine none` collection; within AGREE_DEG and AGREE_M) and
those that do not, right and wrong: how much a second opinion of other features says.

`floor` registers every pair as `byoc register` does (the FPFH fallback included) and, for
each refined registration, also without the refinement's restarts: the confidence before the
restarts (with their most confident cues) against after, and the seconds the restarts took.
`floor-table` prints, for each floor, how many registrations would skip the restarts and
whether any of them would have reached the default gate after them (the choice of
`register.RESTART_FLOOR`).

This file is the entry point; the parts are its siblings: `_confidence_set.py` (the pairs),
`_confidence_records.py` (reading and judging the records), `_confidence_collect.py`,
`_confidence_truth.py` (`check-truth`), `_confidence_fit.py` (`fit`, `agreement`) and
`_confidence_floor.py` (`floor`, `floor-table`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from _confidence_collect import collect
from _confidence_fit import agreement, fit
from _confidence_floor import floor_collect, floor_table
from _confidence_records import determined
from _confidence_set import (
    fragment_pairs,
    negative_pairs,
    part_of_set,
    rgbd_pairs,
    variant_pairs,
)
from _confidence_truth import check_truth, open3d_truth

__all__ = [
    "agreement",
    "check_truth",
    "collect",
    "determined",
    "fit",
    "floor_collect",
    "floor_table",
    "fragment_pairs",
    "main",
    "negative_pairs",
    "open3d_truth",
    "part_of_set",
    "rgbd_pairs",
    "variant_pairs",
]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--part", default="1/1", help="I/N: every N-th pair from the I-th")
    c.add_argument("--groups", nargs="*", default=[], help="only these groups (default: all)")
    c.add_argument(
        "--refine", choices=("none",), help="unrefined results of both features, every pair"
    )
    c.add_argument(
        "--truth-from", type=Path, nargs="*", help="reuse these collections' ground truth"
    )
    f = sub.add_parser("fit")
    f.add_argument("paths", type=Path, nargs="+")
    f.add_argument("--truth", choices=("gt", "refined"), default="refined")
    f.add_argument(
        "--checked", type=Path, nargs="*", help="check-truth output: also score determined pairs"
    )
    a = sub.add_parser("agreement")
    a.add_argument("paths", type=Path, nargs="+")
    a.add_argument("--coarse", type=Path, nargs="+", required=True)
    a.add_argument("--checked", type=Path, nargs="*")
    k = sub.add_parser("check-truth")
    k.add_argument("paths", type=Path, nargs="+")
    k.add_argument("--out", type=Path, required=True)
    k.add_argument("--part", default="1/1", help="I/N: every N-th pair from the I-th")
    g = sub.add_parser("floor")
    g.add_argument("--out", type=Path, required=True)
    g.add_argument("--part", default="1/1", help="I/N: every N-th pair from the I-th")
    t = sub.add_parser("floor-table")
    t.add_argument("paths", type=Path, nargs="+")
    args = parser.parse_args(argv)
    part = tuple(int(x) for x in getattr(args, "part", "1/1").split("/"))
    if args.command in ("floor", "check-truth") and args.out.exists():  # never write over it
        parser.error(f"--out {args.out}: exists; give a new file")
    if args.command == "collect":
        collect(args.out, part, args.groups, args.refine, args.truth_from)
    elif args.command == "floor":
        floor_collect(args.out, part)
    elif args.command == "floor-table":
        floor_table(args.paths)
    elif args.command == "agreement":
        agreement(args.paths, args.coarse, args.checked)
    elif args.command == "check-truth":
        check_truth(args.paths, args.out, part)
    else:
        fit(args.paths, args.truth, args.checked)
    return 0


if __name__ == "__main__":
    sys.exit(main())
