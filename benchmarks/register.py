"""Benchmark of `byoc register` against Open3D FPFH + RANSAC, measured in one run.

Prints, on the 3DMatch sample fragments (or any pair given), at 2.5 cm:
  * per-stage times of the in-process registration (median of repeats) for the `compact` and
    `minkunet34c` encoders (random weights: speed does not depend on the values);
  * Open3D FPFH + RANSAC (tutorial settings: mutual filter, 100k iterations, 0.999) at 5 cm and
    2.5 cm on the same pair, and the speed ratio;
  * the sparse convolution's achieved FLOP/s against a dense matmul of the same width;
  * the peak RSS of the whole `byoc register` command (a subprocess);
  * pairs per second of `byoc register-batch` against a loop of single `byoc register`
    processes on the same pairs (every pair of the sample's fragments; whole processes,
    shipped weights, defaults), and their ratio;
  * whole `byoc register` processes on the pair: the default (shipped weights, learned-feature
    defaults) against `--features fpfh`, interleaved, medians and their ratio;
  * `--baseline SRC`: also the default command of another source tree (e.g. `../main/src`,
    run with `PYTHONPATH=SRC`) interleaved with the others, in the load matrix and the batch
    part: before and after a change, measured in the same minutes;
  * `--only load`: whole processes under load (`--cases`: idle; one core taken by a busy
    loop (`busy`) or every core (`allbusy`); `--copies` copies of each command at once, as
    `xargs -P` runs them (`parallel`)) on three inputs
    (`--inputs`: the fragment pair; the README's demo pair (`demo`); a full-resolution TUM
    depth-frame pair, 640 x 480 PNGs;
    a large pair of 1-2 M points each fused at run time from TUM fr1_desk depth frames with
    their ground-truth poses): the default, `--features fpfh` and Open3D's FPFH + RANSAC
    (benchmarks/o3d_fpfh_ransac.py) interleaved, medians of wall and CPU seconds per command,
    their ratios, and per-stage medians from the `--json` reports.

Usage: python benchmarks/register.py [--repeats 5] [--only batch|whole|load] [SOURCE TARGET]
       python benchmarks/register.py --only load [--cases idle,busy,parallel]
           [--inputs fragment,demo,depth,large] [--copies 3] [--repeats 5]
           [--variants default,fpfh,open3d] [--baseline SRC]
       python benchmarks/register.py --only batch --no-loop [--repeats 3] [--baseline SRC]

This file is the entry point; the parts are its siblings: `_register_stages.py` (in process),
`_register_whole.py` (`--only batch`, `--only whole`), `_register_load.py` (`--only load`) and
`_register_common.py` (what they share).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from _register_common import SAMPLE
from _register_load import DEMO, VARIANTS, Input, depth_pair, large_pair, load_matrix
from _register_stages import print_in_process
from _register_whole import print_batch, whole_process


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "pair",
        nargs="*",
        type=Path,
        default=[SAMPLE / "cloud_bin_0.ply", SAMPLE / "cloud_bin_4.ply"],
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--only",
        choices=["batch", "whole", "load"],
        help="Run only the batch-vs-loop part, the whole-process part or the load matrix.",
    )
    parser.add_argument(
        "--cases", default="idle,busy,parallel", help="Load-matrix cases (also allbusy)."
    )
    parser.add_argument(
        "--inputs", default="fragment,depth,large", help="Load-matrix inputs (also demo)."
    )
    parser.add_argument(
        "--variants", default=",".join(VARIANTS), help="Load-matrix commands (default,fpfh,open3d)."
    )
    parser.add_argument(
        "--baseline",
        type=Path,
        help="Another source tree whose default command runs too (PYTHONPATH), e.g. ../main/src.",
    )
    parser.add_argument("--copies", type=int, default=3, help="Copies at once (parallel case).")
    parser.add_argument(
        "--no-loop", action="store_true", help="Batch part: skip the loop of single registers."
    )
    args = parser.parse_args()
    if args.only == "load":
        with tempfile.TemporaryDirectory() as tmp:
            makers = {
                "fragment": lambda: Input("fragment pair", *args.pair, []),
                "demo": lambda: Input("demo pair", DEMO / "source.ply", DEMO / "target.ply", []),
                "depth": depth_pair,
                "large": lambda: large_pair(Path(tmp)),
            }
            pairs = [makers[name]() for name in args.inputs.split(",")]
            variants = tuple(args.variants.split(","))
            load_matrix(
                pairs, args.cases.split(","), args.copies, args.repeats, variants, args.baseline
            )
        return
    if args.only == "batch":
        print_batch(SAMPLE, args.repeats, loop=not args.no_loop, baseline=args.baseline)
        return
    if args.only == "whole":
        whole_process(*args.pair, args.repeats)
        return
    src_path, tgt_path = args.pair
    print_in_process(src_path, tgt_path, args.repeats)
    print_batch(SAMPLE)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
