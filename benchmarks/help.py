"""How long `byoc --help` and `byoc COMMAND --help` take, against `byoc --version`.

Runs each command as a whole process (`python -m byoc_cli.cli.main ...`, the code of this
tree or of `--src`), `--repeats` times interleaved, and prints the best and the median wall
seconds of each and the ratio of its best to the best of `--version`. The help of every
command should stay within twice `--version` (no torch, open3d or numpy is imported for it;
tests/cli/test_main.py checks the imports, this script the time).

Usage: python benchmarks/help.py [--repeats 5] [--src SRC] [--all]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the commands timed by default (--all: every command's help)
DEFAULT_CASES = (["--version"], ["--help"], ["register", "--help"])
ALL_COMMANDS = (
    "register",
    "register-batch",
    "features",
    "weights",
    "train",
    "eval-fmr",
    "eval-pairs",
    "make-fragments",
    "register-scans",
    "odometry",
)


def run_once(args: list[str], src: Path) -> float:
    """Wall seconds of one ``byoc ARGS`` process (its output discarded)."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    started = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "byoc_cli.cli.main", *args],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        check=True,
    )
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--src", type=Path, default=ROOT / "src", help="the tree to time")
    parser.add_argument("--all", action="store_true", help="every command's --help")
    options = parser.parse_args()
    if options.repeats < 1:
        parser.error("--repeats must be at least 1")
    if not (options.src / "byoc_cli").is_dir():
        parser.error(f"--src {options.src}: no byoc_cli package there")
    cases = list(DEFAULT_CASES)
    if options.all:
        cases += [[name, "--help"] for name in ALL_COMMANDS if name != "register"]
    times: dict[str, list[float]] = {" ".join(c): [] for c in cases}
    for _ in range(options.repeats):  # interleaved: a busy minute touches every case
        for case in cases:
            times[" ".join(case)].append(run_once(case, options.src))
    version = min(times["--version"])
    print(f"load average {os.getloadavg()[0]:.2f}, {options.repeats} repeats, {options.src}")
    print("| command | best s | median s | best / --version |")
    print("|---|---|---|---|")
    for name, values in times.items():
        best, median = min(values), statistics.median(values)
        print(f"| byoc {name} | {best:.3f} | {median:.3f} | {best / version:.2f} |")


if __name__ == "__main__":
    main()
