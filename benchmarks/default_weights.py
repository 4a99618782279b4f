"""The shipped weights against FPFH (two voxel sizes) and a random encoder, on held-out data.

Usage::

    python benchmarks/default_weights.py --out eval/ [--fragments DEV_FRAGMENTS]
        [--columns byoc byoc-random fpfh fpfh-2.5cm] [--weights W ...] [--seeds 0 1 2]
        [--table-only]

Runs, for every pair set, the ``byoc eval-pairs`` / ``byoc eval-fmr`` commands it prints
(one JSON per command in ``--out``; a JSON already there is reused if it was made with the
same weights file, so columns can be run at different times), then prints the Markdown table
of docs/weights.md: rotation accuracy at 5 deg and translation accuracy at 10 cm on the RGB-D
pair sets; FMR, corr-FMR and registration recall (official) on the fragment sets.
``--weights`` adds a column per file (e.g. the best paper-recipe weights). ``--seeds`` runs
every command at each seed (``--seed``: RANSAC's samples, the points sampled per cloud) and
prints the median and, in brackets, the lowest and highest figure over the seeds. Pair sets:
``tum_fr1_desk_full`` at spacing 10 and 20, ``tum_fr3_cabinet`` at spacing 2,
``realsense_tabletop`` at spacing 5, the fragments made from ``tum_fr1_desk_full`` (``byoc
make-fragments ... --frames-per-fragment 25``) and the 3DMatch sample (its 3DMatch pairs, overlap
above 30 %, and its 3DLoMatch pairs, 10 to 30 %).
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import shlex
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

NAMED_COLUMNS = ("byoc", "byoc-random", "fpfh", "fpfh-2.5cm")
PAIR_SETS = [
    ("tum_fr1_desk_full, spacing 10", "rgbd/tum_fr1_desk_full", 10),
    ("tum_fr1_desk_full, spacing 20", "rgbd/tum_fr1_desk_full", 20),
    ("tum_fr3_cabinet, spacing 2", "rgbd/tum_fr3_cabinet", 2),
    ("realsense_tabletop, spacing 5", "rgbd/realsense_tabletop", 5),
]


def _column_args(column: str) -> tuple[list[str], str]:
    """Extra arguments of a column's command and the method name in its JSON."""
    if column == "fpfh":
        return ["--method", "fpfh-ransac"], "fpfh-ransac"
    if column == "fpfh-2.5cm":
        return ["--method", "fpfh-ransac", "--fpfh-voxel-size", "0.025"], "fpfh-ransac"
    if column in ("byoc", "byoc-random"):
        return ["--method", column], column
    return ["--method", "byoc", "--weights", column], "byoc"


def _slug(column: str, seed: int = 0) -> str:
    """The JSON name part of a column at a seed (seed 0 has none: the single-seed files)."""
    name = Path(column).stem if column.endswith(".safetensors") else column
    return name if seed == 0 else f"{name}-seed{seed}"


def _figure(values: list[float]) -> str:
    """A percentage over seeds: the value, or the median and [lowest-highest] of several."""
    if len(values) == 1:
        return f"{values[0]:.1f}"
    ordered = sorted(values)
    median = statistics.median(ordered)
    return f"{median:.1f} [{ordered[0]:.1f}-{ordered[-1]:.1f}]"


def _check_inputs(columns: list[str], fragments: Path | None) -> str | None:
    """What is wrong with the columns and fragments asked for, before anything runs (None: all
    good): a column is one of the named ones or an existing weights file."""
    for column in columns:
        if column not in NAMED_COLUMNS and not Path(column).is_file():
            named = ", ".join(NAMED_COLUMNS)
            return f"column {column!r}: neither {named} nor an existing weights file"
    if fragments is not None and not fragments.is_dir():
        return f"--fragments {fragments}: no such folder"
    return None


@functools.cache
def _weights_sha256(column: str) -> str | None:
    """SHA-256 of the weights file a learned column uses (None: FPFH and the random encoder)."""
    if column in ("fpfh", "fpfh-2.5cm", "byoc-random"):
        return None
    if column == "byoc":
        from byoc_cli.pipeline.default_weights import default_weights_path

        path = default_weights_path()
    else:
        path = Path(column)
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _reusable(out: Path, sha256: str | None) -> bool:
    """A JSON of an earlier run counts only if it was made with the same weights file."""
    if not out.exists():
        return False
    if sha256 is None:
        return True
    methods = json.loads(out.read_text()).get("methods", [])
    return all(m.get("features_info", {}).get("file_sha256") == sha256 for m in methods)


def _run(command: list[str], out: Path, sha256: str | None = None) -> dict:
    if not _reusable(out, sha256):
        if out.exists():
            print(f"{out.name}: made with other weights, measured again", file=sys.stderr)
        print("$ " + shlex.join(command), file=sys.stderr, flush=True)
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return json.loads(out.read_text())


def _pairs_job(
    out_dir: Path, rel: str, spacing: int, column: str, extra: list[str], seed: int
) -> tuple[Path, list[str]]:
    """The JSON path and ``byoc eval-pairs`` command of a column on a pair set at a seed."""
    out = out_dir / f"pairs-{Path(rel).name}-{spacing}-{_slug(column, seed)}.json"
    seeded = ["--seed", str(seed)] if seed else []
    command = [
        "byoc", "eval-pairs", "--rgbd-dir", str(DATA / rel), "--spacing", str(spacing),
        *extra, *seeded, "--json", str(out), "--quiet",
    ]  # fmt: skip
    return out, command


def _fmr_job(
    out_dir: Path, root: Path, gt: list[str], column: str, extra: list[str], seed: int
) -> tuple[Path, list[str]]:
    """The JSON path and ``byoc eval-fmr`` command of a column on a fragment set at a seed."""
    out = out_dir / f"fmr-{Path(root).name}-{_slug(column, seed)}.json"
    seeded = ["--seed", str(seed)] if seed else []
    command = [
        "byoc", "eval-fmr", str(root), *gt, *extra, *seeded, "--json", str(out), "--quiet",
    ]  # fmt: skip
    return out, command


def _over_seeds(args: argparse.Namespace, column: str, method: str, job) -> list[dict] | None:
    """The results of ``method`` for every seed of ``--seeds``; ``job(seed)`` gives the JSON path
    and the command. None when ``--table-only`` finds a seed's JSON missing (a "-" cell)."""
    sha256 = _weights_sha256(column)
    runs = []
    for seed in args.seeds:
        out, command = job(seed)
        if args.table_only and not _reusable(out, sha256):
            return None
        runs.append(_run(command, out, sha256)["results"][method])
    return runs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--fragments", type=Path, default=None)
    parser.add_argument(
        "--columns", nargs="+", default=["byoc", "fpfh", "fpfh-2.5cm", "byoc-random"]
    )
    parser.add_argument("--weights", type=Path, nargs="*", default=[])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--table-only", action="store_true")
    args = parser.parse_args()
    columns = list(args.columns) + [str(w) for w in args.weights]
    problem = _check_inputs(columns, args.fragments)
    if problem:
        parser.error(problem)
    args.out.mkdir(parents=True, exist_ok=True)
    labels = {
        "byoc": "shipped default",
        "byoc-random": "random init",
        "fpfh": "fpfh (5 cm)",
        "fpfh-2.5cm": "fpfh (2.5 cm)",
    }

    rows = []
    for name, rel, spacing in PAIR_SETS:
        cells = []
        for column in columns:
            extra, method = _column_args(column)
            job = functools.partial(_pairs_job, args.out, rel, spacing, column, extra)
            runs = _over_seeds(args, column, method, job)
            if runs is None:
                cells.append("-")
                continue
            rot = [r["rotation_deg"]["accuracy_percent"]["5"] for r in runs]
            trans = [r["translation_cm"]["accuracy_percent"]["10"] for r in runs]
            cells.append(f"{_figure(rot)} / {_figure(trans)}")
        rows.append((f"{name}: rot@5° / trans@10cm %", cells))
    fragment_sets = [
        (
            "3DMatch sample",
            DATA / "3dmatch/sample/3DMatch",
            ["--gt-dir", str(DATA / "3dmatch/benchmarks/3DMatch")],
        ),
        (
            "3DLoMatch sample",
            DATA / "3dmatch/sample/3DLoMatch",
            ["--gt-dir", str(DATA / "3dmatch/benchmarks/3DLoMatch")],
        ),
    ]
    if args.fragments:
        fragment_sets.insert(0, ("fragments of tum_fr1_desk_full", args.fragments, []))
    for name, root, gt in fragment_sets:
        cells = []
        for column in columns:
            extra, method = _column_args(column)
            job = functools.partial(_fmr_job, args.out, root, gt, column, extra)
            runs = _over_seeds(args, column, method, job)
            if runs is None:
                cells.append("-")
                continue
            figures = [
                [100 * r[key]["pooled"] for r in runs]
                for key in ("fmr", "corr_fmr", "registration_recall")
            ]
            cells.append(" / ".join(_figure(f) for f in figures))
        rows.append((f"{name}: FMR / corr-FMR / RR %", cells))
    header = "| pair set | " + " | ".join(labels.get(c, Path(c).name) for c in columns) + " |"
    print(header)
    print("|" + "---|" * (len(columns) + 1))
    for name, cells in rows:
        print(f"| {name} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
