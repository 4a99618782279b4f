"""How registration time and memory grow with the size of LiDAR-like scans.

On the simulated street pairs of ``benchmarks/scan_sim.py`` (10k to 1M points per scan), each
method runs as its own child process, under a timeout and an address-space cap
(``RLIMIT_AS``), and is measured from the child's own rusage (``os.wait4``): wall seconds, CPU
seconds (user + system), peak RSS. Methods:

* ``byoc``: ``byoc register SRC TGT -o T.txt --json r.json`` (no other flag);
* ``fpfh``: the same with ``--features fpfh``;
* ``o3d``: Open3D's FPFH + RANSAC at a hand-set voxel (``benchmarks/o3d_fpfh_ransac.py``;
  the pair's ``info.json`` voxel: 0.3 m for the street, 1/50 of the object's size for
  objects; ``--voxel`` overrides it).

Per run: the exit code (or ``timeout`` / ``out of memory``), rotation and translation error of
``T`` against ``T_gt`` (the translation error at the source's median point, so that a 1 deg
error on georeferenced coordinates does not read as kilometres; the JSON also has it at the
origin), the confidence of byoc's JSON report. The table gives medians over
``--repeat`` runs and each finished method's wall time over Open3D's on the same pair; then, per
method, the slope of log(wall) against log(points) fitted over the street sizes that finished
(exit 0 or 3).

Usage::

    nice -n 10 python benchmarks/scaling.py [--sizes 10000 30000 100000 300000 1000000]
        [--methods byoc fpfh o3d] [--data DIR] [--pairs DIR ...] [--repeat 1]
        [--timeout 600] [--mem-gb 8] [--pythonpath SRC] [--json OUT]

``--data DIR`` keeps the generated street pairs (``DIR/street-<size>``; reused when they were
made with the same settings), else they go to a temporary folder. ``--pairs`` adds pair folders
written by ``scan_sim.py`` (``source.ply``, ``target.ply``, ``T_gt.txt``, ``info.json``).
``--pythonpath SRC`` runs the byoc methods with ``PYTHONPATH=SRC`` (another source tree).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import scan_sim  # noqa: E402

METHODS = ("byoc", "fpfh", "o3d")
SIZES = (10000, 30000, 100000, 300000, 1000000)
OUT_OF_MEMORY = (
    "MemoryError",
    "Unable to allocate",
    "Cannot allocate memory",
    "can't allocate memory",
    "bad_alloc",
    "out of memory",
    "failed to map segment",  # a shared library that no longer fits under the cap
)


class Child(NamedTuple):
    """What one child process did."""

    wall: float  # s
    cpu: float  # s, user + system of the child (and its children)
    peak_mb: float  # peak resident set of the child (and its largest child)
    exit: int | None  # exit code (negative: killed by that signal); None: timed out
    status: str  # ok, below gate, timeout, out of memory, error N, signal N
    stdout: str
    stderr: str


def _limits(mem_bytes: int):
    """A ``preexec_fn`` that caps the child's address space at ``mem_bytes``."""

    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (mem_bytes, mem_bytes))

    return apply


def _status(code: int, stderr: str) -> str:
    """The status of a child that ended with ``code`` (``os.waitstatus_to_exitcode``)."""
    if code == 0:
        return "ok"
    if code == 3:
        return "below gate"
    if any(sign in stderr for sign in OUT_OF_MEMORY):
        return "out of memory"
    return f"signal {-code}" if code < 0 else f"error {code}"


def run_child(
    command: list[str], timeout: float, mem_bytes: int, folder: Path, env: dict | None = None
) -> Child:
    """Run ``command`` in ``folder`` (its own process group) under an address-space cap of
    ``mem_bytes``; kill its group after ``timeout`` s. Measured from its rusage."""
    out, err = folder / "stdout.txt", folder / "stderr.txt"
    with out.open("w") as stdout, err.open("w") as stderr:
        start = time.perf_counter()
        proc = subprocess.Popen(
            command,
            cwd=folder,
            stdout=stdout,
            stderr=stderr,
            env=env,
            start_new_session=True,
            preexec_fn=_limits(mem_bytes),
        )
        killed = threading.Event()

        def kill() -> None:
            killed.set()
            os.killpg(proc.pid, signal.SIGKILL)

        timer = threading.Timer(timeout, kill)
        timer.start()
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        except BaseException:
            os.killpg(proc.pid, signal.SIGKILL)
            raise
        finally:
            timer.cancel()
        wall = time.perf_counter() - start
    code = os.waitstatus_to_exitcode(status)
    proc.returncode = code  # reaped by wait4
    text = err.read_text(errors="replace")
    return Child(
        wall,
        usage.ru_utime + usage.ru_stime,
        usage.ru_maxrss / 1024.0,
        None if killed.is_set() else code,
        "timeout" if killed.is_set() else _status(code, text),
        out.read_text(errors="replace"),
        text,
    )


def errors(T: np.ndarray, T_gt: np.ndarray, at=(0.0, 0.0, 0.0)) -> tuple[float, float]:
    """Rotation error (deg) and translation error (units of the points) of ``T (4, 4)``
    against ``T_gt (4, 4)``: the angle of ``R_gt^T R`` and how far apart the two send the
    point ``at (3,)``, ``|(R - R_gt) at + t - t_gt|`` (``|t - t_gt|`` at the origin)."""
    cos = (np.trace(T_gt[:3, :3].T @ T[:3, :3]) - 1) / 2
    at = np.asarray(at, dtype=np.float64)
    apart = (T[:3, :3] - T_gt[:3, :3]) @ at + T[:3, 3] - T_gt[:3, 3]
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), float(np.linalg.norm(apart))


def median_point(path: Path) -> np.ndarray:
    """The per-axis median ``(3,)`` of a PLY's vertices (a stray point does not move it)."""
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"]
    return np.array([np.median(np.asarray(vertex[axis], dtype=np.float64)) for axis in "xyz"])


def command(method: str, pair: Path, voxel: float) -> list[str]:
    """The command line of ``method`` on the pair folder ``pair``, writing ``T.txt`` (and
    byoc's ``r.json``) into the current folder."""
    src, tgt = str(pair / "source.ply"), str(pair / "target.ply")
    if method == "o3d":
        script = str(HERE / "o3d_fpfh_ransac.py")
        return [sys.executable, script, src, tgt, "--voxel", repr(voxel), "-o", "T.txt"]
    byoc = [sys.executable, "-m", "byoc_cli.cli.main", "register", src, tgt]
    extra = ["--features", "fpfh"] if method == "fpfh" else []
    return [*byoc, "-o", "T.txt", "--json", "r.json", *extra]


def measure(method: str, pair: Path, args: argparse.Namespace) -> dict:
    """One run of ``method`` on ``pair``: a row of the table (before the medians)."""
    info = json.loads((pair / "info.json").read_text())
    voxel = args.voxel if args.voxel is not None else info.get("voxel", scan_sim.STREET_VOXEL)
    env = None
    if args.pythonpath is not None and method != "o3d":
        paths = [str(args.pythonpath), os.environ.get("PYTHONPATH", "")]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in paths if p)}
    with tempfile.TemporaryDirectory(prefix="scaling-") as tmp:
        folder = Path(tmp)
        child = run_child(
            command(method, pair, voxel), args.timeout, int(args.mem_gb * 2**30), folder, env
        )
        row = {
            "pair": pair.name,
            "points": (info["points_src"] + info["points_tgt"]) / 2,
            "kind": info.get("kind"),
            "variant": info.get("variant"),
            "asked": info.get("asked_points_per_scan"),
            "method": method,
            "wall_s": child.wall,
            "cpu_s": child.cpu,
            "peak_mb": child.peak_mb,
            "exit": child.exit,
            "status": child.status,
            "rot_deg": None,
            "trans": None,
            "confidence": None,
        }
        if method == "o3d":
            row["voxel"] = voxel
        if (folder / "T.txt").exists() and child.status in ("ok", "below gate"):
            T = np.loadtxt(folder / "T.txt").reshape(4, 4)
            T_gt = np.loadtxt(pair / "T_gt.txt")
            row["rot_deg"], row["trans"] = errors(T, T_gt, median_point(pair / "source.ply"))
            row["trans_at_origin"] = errors(T, T_gt)[1]
        if (folder / "r.json").exists():
            report = json.loads((folder / "r.json").read_text())
            row["confidence"] = report.get("confidence")
            row["stages_s"] = report.get("timings_s")
        elif method == "o3d" and child.status == "ok":
            row["stages_s"] = json.loads(child.stdout.strip().splitlines()[-1])
        if child.status not in ("ok", "below gate"):
            row["stderr_tail"] = child.stderr[-400:]
    return row


def _median_row(runs: list[dict]) -> dict:
    """The row of several runs of one method on one pair: medians of the numbers; the
    status of every run when they differ."""
    row = dict(runs[0])
    for key in ("wall_s", "cpu_s", "peak_mb", "rot_deg", "trans", "confidence"):
        values = [r[key] for r in runs if r[key] is not None]
        row[key] = statistics.median(values) if values else None
    statuses = sorted({r["status"] for r in runs})
    row["status"] = statuses[0] if len(statuses) == 1 else "/".join(statuses)
    row["runs"] = len(runs)
    return row


def street_pairs(sizes: list[int], folder: Path, seed: int) -> list[Path]:
    """The street pair folders ``folder/street-<size>`` (scan_sim's defaults, ``seed``),
    written unless one made with the same settings is there."""
    pairs = []
    for n in sizes:
        pair = folder / f"street-{scan_sim.size_name(n)}"
        settings = scan_sim.street_settings(n, seed)
        if (pair / "info.json").exists():
            info = json.loads((pair / "info.json").read_text())
            if "variant" not in info and all(info.get(k) == v for k, v in settings.items()):
                pairs.append(pair)
                continue
        made, info = scan_sim.made_street(n, seed)
        info = scan_sim.write_pair(pair, made, info)
        print(f"wrote {pair}: {info['points_src']} + {info['points_tgt']} points", file=sys.stderr)
        pairs.append(pair)
    return pairs


def _cell(value, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def table(rows: list[dict]) -> str:
    """The markdown table of ``rows``: one line per pair and method."""
    o3d = {r["pair"]: r["wall_s"] for r in rows if r["method"] == "o3d" and r["status"] == "ok"}
    lines = [
        "| pair | points | method | wall s | CPU s | peak MB | exit | status | rot deg | trans "
        "| conf | x o3d |",
        "|---|---:|---|---:|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        done = r["status"] in ("ok", "below gate") and r["pair"] in o3d
        ratio = r["wall_s"] / o3d[r["pair"]] if done else None
        lines.append(
            f"| {r['pair']} | {r['points']:.0f} | {r['method']} | {r['wall_s']:.2f} "
            f"| {r['cpu_s']:.2f} | {r['peak_mb']:.0f} | {_cell(r['exit'], 'd')} "
            f"| {r['status']} | {_cell(r['rot_deg'], '.2f')} | {_cell(r['trans'], '.3g')} "
            f"| {_cell(r['confidence'], '.3f')} | {_cell(ratio, '.2f')} |"
        )
    return "\n".join(lines)


def slopes(rows: list[dict]) -> dict[str, float | None]:
    """Per method, the least-squares slope of log(wall) on log(points) over its rows of street
    pairs (not their variants) that finished (exit 0 or 3); None with fewer than two sizes."""
    fitted = {}
    for method in dict.fromkeys(r["method"] for r in rows):
        done = [
            r
            for r in rows
            if r["method"] == method
            and r["kind"] == "street"
            and r.get("variant") is None
            and r["status"] in ("ok", "below gate")
        ]
        sizes = {r["points"] for r in done}
        if len(sizes) < 2:
            fitted[method] = None
            continue
        x = np.log([r["points"] for r in done])
        y = np.log([r["wall_s"] for r in done])
        fitted[method] = float(np.polyfit(x, y, 1)[0])
    return fitted


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes",
        nargs="*",
        type=int,
        default=list(SIZES),
        help="points per scan of the street pairs",
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        default=list(METHODS),
        metavar="METHOD",
        help=f"of {', '.join(METHODS)}",
    )
    parser.add_argument(
        "--pairs", nargs="+", type=Path, default=[], help="more pair folders written by scan_sim.py"
    )
    parser.add_argument("--data", type=Path, help="where the street pairs are kept")
    parser.add_argument("--seed", type=int, default=0, help="of the street scene")
    parser.add_argument("--voxel", type=float, help="o3d's voxel (default: the pair's)")
    parser.add_argument("--repeat", type=int, default=1, help="runs per method and pair")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per run")
    parser.add_argument("--mem-gb", type=float, default=8.0, help="address-space cap per run")
    parser.add_argument("--pythonpath", type=Path, help="source tree of the byoc methods")
    parser.add_argument("--json", type=Path, help="write the rows and slopes here")
    args = parser.parse_args(argv)
    # the children run in folders of their own: paths from here on are absolute
    args.pairs = [pair.resolve() for pair in args.pairs]
    args.data = args.data.resolve() if args.data is not None else None
    for method in args.methods:
        if method not in METHODS:
            parser.error(f"--methods {method!r}: not one of {', '.join(METHODS)}")
    for pair in args.pairs:
        if not all(
            (pair / name).exists() for name in ("source.ply", "target.ply", "T_gt.txt", "info.json")
        ):
            parser.error(f"--pairs {pair}: no source.ply, target.ply, T_gt.txt and info.json")
    if not args.sizes and not args.pairs:
        parser.error("nothing to run: give --sizes or --pairs")
    if args.repeat < 1 or args.timeout <= 0 or args.mem_gb <= 0:
        parser.error("--repeat, --timeout and --mem-gb must be positive")
    return args


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    with tempfile.TemporaryDirectory(prefix="scaling-pairs-") as tmp:
        data = args.data if args.data is not None else Path(tmp)
        pairs = street_pairs(args.sizes, data, args.seed) + list(args.pairs)
        runs: dict[tuple[str, str], list[dict]] = {}
        for k in range(args.repeat):
            for pair in pairs:
                for method in args.methods:
                    row = measure(method, pair, args)
                    print(
                        f"[{k + 1}/{args.repeat}] {pair.name} {method}: {row['status']}, "
                        f"{row['wall_s']:.1f} s, {row['peak_mb']:.0f} MB",
                        file=sys.stderr,
                        flush=True,
                    )
                    runs.setdefault((pair.name, method), []).append(row)
    rows = [_median_row(r) for r in runs.values()]
    print(table(rows))
    fitted = slopes(rows)
    print()
    print("slope of log(wall) on log(points), street sizes that finished:")
    for method, slope in fitted.items():
        print(f"  {method}: {_cell(slope, '.2f')}")
    if args.json is not None:
        settings = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
        settings["pairs"] = [str(p) for p in args.pairs]
        report = {"settings": settings, "rows": rows, "slopes": fitted}
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
