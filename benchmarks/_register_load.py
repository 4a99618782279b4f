"""`benchmarks/register.py --only load`: whole processes under load (idle, one or every core
busy, copies at once) on the fragment, demo, depth-frame and large pairs: the default,
`--features fpfh` and Open3D's FPFH + RANSAC interleaved.
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from _register_common import BYOC, DATA, source_env

TUM_DEPTH = DATA / "rgbd" / "tum_fr3_cabinet"  # Kinect (fr3), 640 x 480, keyframes
TUM_LARGE = DATA / "rgbd" / "tum_fr1_desk_full"  # Kinect (fr1), every second frame
#: frames of TUM_LARGE fused into the source and the target of the large pair
LARGE_FRAMES = ((0, 2, 4, 6, 8), (10, 12, 14, 16, 18))
O3D_PEER = Path(__file__).resolve().parent / "o3d_fpfh_ransac.py"
VARIANTS = ("default", "fpfh", "open3d")
#: the README's demo pair
DEMO = DATA / "pairs" / "3dmatch_demo"


class Input(NamedTuple):
    """A pair to register: its name, the two files and the options they need."""

    name: str
    source: Path
    target: Path
    options: list[str]


def _tum_depth_files(folder: Path) -> list[tuple[float, Path]]:
    rows = []
    for line in (folder / "depth.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            stamp, name = line.split()[:2]
            rows.append((float(stamp), folder / name))
    return rows


def depth_pair() -> Input:
    """The first two keyframes of TUM fr3_cabinet, as the 16-bit PNGs a Kinect writes."""
    (_, a), (_, b) = _tum_depth_files(TUM_DEPTH)[:2]
    options = ["--intrinsics", str(TUM_DEPTH / "intrinsics.json"), "--depth-scale", "5000"]
    return Input("depth-frame pair", a, b, options)


def large_pair(folder: Path) -> Input:
    """Two clouds of 1-2 M points each: five TUM fr1_desk depth frames each, back-projected
    and put into the camera frame of the first with the ground-truth poses (NPY files)."""
    from byoc_cli.io.depth import read_depth_cloud
    from byoc_cli.io.trajectory import read_tum_trajectory

    files = _tum_depth_files(TUM_LARGE)
    stamps, poses = read_tum_trajectory(TUM_LARGE / "groundtruth.txt")
    paths = []
    for k, frames in enumerate(LARGE_FRAMES):
        clouds, first = [], None
        for index in frames:
            stamp, path = files[index]
            T_world_cam = poses[int(np.argmin(np.abs(stamps - stamp)))]
            first = T_world_cam if first is None else first
            T = np.linalg.inv(first) @ T_world_cam
            points = read_depth_cloud(path, TUM_LARGE / "intrinsics.json", 5000.0).points
            clouds.append(points @ T[:3, :3].T + T[:3, 3])
        paths.append(folder / f"large_{k}.npy")
        np.save(paths[-1], np.concatenate(clouds))
    return Input("large pair", paths[0], paths[1], [])


def _command(variant: str, pair: Input, out: Path) -> list[str]:
    """The command of a variant: ``default``, ``baseline`` (the default, of the baseline
    tree: :func:`source_env`), ``fpfh`` or ``open3d``."""
    if variant == "open3d":
        extra = pair.options
        return [sys.executable, str(O3D_PEER), str(pair.source), str(pair.target), *extra]
    features = ["--features", "fpfh"] if variant == "fpfh" else []
    files = ["-o", str(out / "T.txt"), "--json", str(out / "report.json")]
    return [*BYOC, "register", str(pair.source), str(pair.target), *pair.options, *features, *files]


def _run_copies(
    variant: str, pair: Input, copies: int, tmp: Path, baseline: Path | None = None
) -> tuple[float, float, dict]:
    """``copies`` processes of one command at once: wall seconds until the last ends, median
    CPU seconds (user + system) per process, and the first copy's stage timings."""
    env = source_env(baseline) if variant == "baseline" else None
    outs = [tmp / f"{variant}_{k}" for k in range(copies)]
    for out in outs:
        out.mkdir(exist_ok=True)
    start = time.perf_counter()
    procs = [
        subprocess.Popen(_command(variant, pair, out), stdout=subprocess.PIPE, text=True, env=env)
        for out in outs
    ]
    cpu, stdout = [], []
    for proc in procs:
        text = proc.stdout.read()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode not in (0, 3):
            raise SystemExit(f"{variant} on the {pair.name} exited {proc.returncode}")
        cpu.append(usage.ru_utime + usage.ru_stime)
        stdout.append(text)
    wall = time.perf_counter() - start
    if variant == "open3d":
        stages = json.loads(stdout[0].strip().splitlines()[-1])
    else:
        stages = json.loads((outs[0] / "report.json").read_text())["timings_s"]
    return wall, statistics.median(cpu), stages


@contextlib.contextmanager
def _case(name: str):
    """The machine state of a case: ``busy`` takes one core with a busy loop, ``allbusy``
    every core (one busy loop per CPU)."""
    count = {"busy": 1, "allbusy": os.cpu_count() or 1}.get(name, 0)
    loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        yield
    finally:
        for loop in loops:
            loop.kill()
            loop.wait()


def load_matrix(
    pairs: list[Input],
    cases: list[str],
    copies: int,
    repeats: int,
    variants: tuple[str, ...] = VARIANTS,
    baseline: Path | None = None,
) -> None:
    """Whole processes of every variant on every pair in every case, interleaved; prints
    medians, ratios and stages (and whether the default's T file is the baseline's)."""
    if baseline is not None and "baseline" not in variants:
        variants = (*variants, "baseline")
    for case in cases:
        n = copies if case == "parallel" else 1
        for pair in pairs:
            runs: dict[str, list] = {v: [] for v in variants}
            load_before = os.getloadavg()[0]
            same = None
            with _case(case), tempfile.TemporaryDirectory() as tmp:
                for _ in range(repeats):
                    for variant in variants:
                        runs[variant].append(_run_copies(variant, pair, n, Path(tmp), baseline))
                if "baseline" in variants and "default" in variants:
                    same = (Path(tmp) / "default_0" / "T.txt").read_bytes() == (
                        Path(tmp) / "baseline_0" / "T.txt"
                    ).read_bytes()
            _print_matrix_row(case, n, pair, runs, load_before, os.getloadavg()[0])
            if same is not None:
                print(f"  default's T file byte-identical to the baseline's: {same}")


def _print_matrix_row(case, copies, pair, runs, load_before, load_after) -> None:
    med = {
        v: (statistics.median(r[0] for r in rs), statistics.median(r[1] for r in rs))
        for v, rs in runs.items()
    }
    what = {
        "idle": "idle",
        "busy": "one core busy",
        "allbusy": "every core busy",
        "parallel": f"{copies} copies at once",
    }[case]
    print(
        f"\n{pair.name} ({pair.source.name} -> {pair.target.name}), {what}, median of "
        f"{len(runs['default'])} (load average {load_before:.2f} -> {load_after:.2f}):"
    )
    peers = [p for p in ("fpfh", "open3d", "baseline") if p in med]
    for v, (w, c) in med.items():
        ratios = "".join(
            f"   / {p}: wall {w / med[p][0]:.2f} CPU {c / med[p][1]:.2f}" for p in peers if p != v
        )
        print(f"  {v:<8} wall {w:6.2f} s  CPU {c:6.2f} s per process{ratios}")
    for v, rs in runs.items():
        names = rs[0][2].keys()
        stages = {k: statistics.median(r[2].get(k, float("nan")) for r in rs) for k in names}
        print(f"  {v} stages: " + ", ".join(f"{k} {t:.2f}" for k, t in stages.items()))
