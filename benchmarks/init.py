"""`byoc register --init`: registration from an initial pose, against Open3D and the global
default, on posed RGB-D pairs of ../shared/data (docs/poses.md).

`bench` (the default): the pairs of `_init_pairs.BENCH_SETS` (Kinect pairs 50 camera frames
apart and RealSense tabletop pairs, at most --pairs), each from a guess perturbed from its
ground truth by a random rotation of --near-deg about the source's centroid and a translation
of --near-m (seeded), and from a guess perturbed by --far-deg (outside the trust region).
Methods, all in this process except the batch timing:

* ``byoc --init``: `Registrar.register(src, tgt, init=T)`, what `byoc register --init` runs;
* ``open3d``: Open3D's multiscale point-to-plane ICP from the same guess (voxels 10, 5 and
  2.5 cm, correspondences within 1.5 voxels, 30 iterations each: the levels of
  `pipeline/posegraph.py`) and a wider one (voxels 20, 10, 5 and 2.5 cm, within 2 voxels);
* ``byoc global``: `Registrar.register(src, tgt)` without the guess (the default);
* ``refinement only``: the multiscale point-to-plane refinement of `byoc register` alone from
  the guess (the local path without its coarse pass).

Each result is judged against the ground truth (within 5 deg / 10 cm and 2 deg / 5 cm) and
against the truth refined on the data (`_init_pairs.refined_truth`, where the data determine
it: the refinements of the ground truth agree and at least 30 % of the source overlaps the
target under it); a result "exits 0" when it passes the gate. A line per overlap band counts
the right results (refined truth, 5 deg / 10 cm) of `byoc --init` and `byoc global`. Then
`register-batch` runs twice on the same pairs (PLY files in a temporary folder, the CLI of this
source tree in a subprocess), with and without the init column, and the wall times are
compared.

`collect` and `fit`: the calibration of the local confidence (`_init_calibration.py`);
`sweep`: right results by the size of the guess's error, behind the default trust region
(`_init_sweep.py`).

Usage:
    python benchmarks/init.py [bench] [--pairs 28] [--seed 0] [--json OUT.json]
    python benchmarks/init.py batch [--repeats 3]    # the register-batch timing alone
    python benchmarks/init.py collect --out calib.jsonl
    python benchmarks/init.py fit calib.jsonl [more.jsonl ...]
    python benchmarks/init.py sweep [--pairs 28]

Keep it bounded: `timeout 3600 bash -c 'ulimit -v 8000000; python benchmarks/init.py'`.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from _init_calibration import collect, fit
from _init_pairs import MIN_OVERLAP, ROOT, errors, overlap, perturbed, refined_truth, rgbd_pairs
from _init_sweep import sweep

#: Open3D's multiscale point-to-plane ICP: (voxel m, correspondence distance m, iterations)
OPEN3D_LEVELS = {
    "open3d": ((0.10, 0.15, 30), (0.05, 0.075, 30), (0.025, 0.0375, 30)),
    "open3d wide": ((0.20, 0.40, 30), (0.10, 0.20, 30), (0.05, 0.10, 30), (0.025, 0.05, 30)),
}
BYOC = [sys.executable, "-m", "byoc_cli.cli.main", "-q"]


def open3d_icp(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, levels) -> np.ndarray:
    """Open3D's multiscale point-to-plane ICP of ``src`` onto ``tgt`` from ``T (4, 4)``."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    for voxel, distance, iterations in levels:
        clouds = []
        for points in (src, tgt):
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            cloud = cloud.voxel_down_sample(voxel)
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(2 * voxel, 30))
            clouds.append(cloud)
        T = reg.registration_icp(
            *clouds,
            distance,
            T,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=iterations),
        ).transformation
    return np.asarray(T)


def refinement_only(registrar, src: np.ndarray, tgt: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The multiscale point-to-plane refinement of `byoc register` alone from ``T (4, 4)``,
    at the pair's refinement voxel: the local path without its coarse pass and its choice."""
    import torch

    from byoc_cli.pipeline.refine import refine_multiscale

    voxel = registrar.choose_voxel(src, tgt).refine_voxel
    clouds = torch.from_numpy(src), torch.from_numpy(tgt)
    return refine_multiscale(*clouds, torch.from_numpy(T), voxel).T_tgt_src.numpy()


def _timed(fn):
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = fn()
    return out, time.perf_counter() - start


def _methods(registrar, src, tgt, near, far) -> dict[str, tuple]:
    """``{method: (T, passed or None, seconds)}`` of one pair."""
    from functools import partial

    results = {}
    for label, T_init in (("byoc --init", near), ("byoc --init far", far)):
        r, seconds = _timed(partial(registrar.register, src, tgt, init=T_init))
        results[label] = (r.T_tgt_src, r.passed, seconds)
    for label, levels in OPEN3D_LEVELS.items():
        T, seconds = _timed(partial(open3d_icp, src, tgt, near, levels))
        results[label] = (T, None, seconds)
    T, seconds = _timed(partial(refinement_only, registrar, src, tgt, near))
    results["refinement only"] = (T, None, seconds)
    r, seconds = _timed(partial(registrar.register, src, tgt))
    results["byoc global"] = (r.T_tgt_src, r.passed, seconds)
    return results


def run_pairs(args) -> tuple[list[dict], list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """Every method on every pair; the records and each pair's (source, target, near guess)."""
    from byoc_cli.api import Registrar

    registrar = Registrar(device="cpu")
    rng = np.random.default_rng(args.seed)
    records, kept = [], []
    for pair in rgbd_pairs(limit=args.pairs):
        src, tgt = pair.load_source(), pair.load_target()
        voxel = registrar.choose_voxel(src, tgt).refine_voxel
        truth, determined = refined_truth(src, tgt, pair.T_gt, voxel)
        centroid = src.mean(axis=0)
        near = perturbed(pair.T_gt, centroid, args.near_deg, args.near_m, rng)
        far = perturbed(pair.T_gt, centroid, args.far_deg, args.near_m, rng)
        results = _methods(registrar, src, tgt, near, far)
        shared = overlap(src, tgt, truth)
        record = {
            "pair": pair.name,
            "group": pair.group,
            "determined": determined and shared >= MIN_OVERLAP,
            "overlap": shared,
        }
        for label, (T, passed, seconds) in results.items():
            record[label] = {
                "T": np.asarray(T).tolist(),
                "passed": passed,
                "seconds": seconds,
                "gt": errors(np.asarray(T), pair.T_gt),
                "refined": errors(np.asarray(T), truth),
            }
        records.append(record)
        kept.append((src, tgt, near))
        cells = " ".join(
            f"{k}={v['gt'][0]:.1f}d/{100 * v['gt'][1]:.0f}cm" for k, v in record.items()
            if isinstance(v, dict)
        )  # fmt: skip
        print(f"{pair.name:36s} {cells}", file=sys.stderr, flush=True)
    return records, kept


def batch_pairs(args) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each pair's (source, target, near guess), the guesses drawn as :func:`run_pairs` draws
    them (the same seed gives the same guesses), without running the methods."""
    rng = np.random.default_rng(args.seed)
    kept = []
    for pair in rgbd_pairs(limit=args.pairs):
        src, tgt = pair.load_source(), pair.load_target()
        centroid = src.mean(axis=0)
        near = perturbed(pair.T_gt, centroid, args.near_deg, args.near_m, rng)
        perturbed(pair.T_gt, centroid, args.far_deg, args.near_m, rng)  # the far guess's draw
        kept.append((src, tgt, near))
    return kept


def batch_times(kept, folder: Path, repeats: int = 3) -> dict[str, float]:
    """Median wall seconds of `register-batch` on the pairs without and with the init column
    (``repeats`` runs of each, interleaved, outputs overwritten), and the median of the
    runs' ratios."""
    from byoc_cli.io import format_transform, write_ply

    lines = {"global": [], "init": []}
    for k, (src, tgt, near) in enumerate(kept):
        s, t, g = folder / f"{k}_src.ply", folder / f"{k}_tgt.ply", folder / f"{k}_init.txt"
        write_ply(s, src)
        write_ply(t, tgt)
        g.write_text(format_transform(near))
        lines["global"].append(f"{s} {t} {folder / f'{k}_global.txt'}")
        lines["init"].append(f"{s} {t} {folder / f'{k}_local.txt'} {g}")
    runs = {kind: [] for kind in lines}
    for _ in range(repeats):
        for kind, listing in lines.items():
            path = folder / f"{kind}.txt"
            path.write_text("\n".join(listing) + "\n")
            env = {"PYTHONPATH": str(ROOT / "src")}
            summary = str(folder / f"{kind}.jsonl")
            command = [*BYOC, "register-batch", str(path), "--summary", summary, "--overwrite"]
            start = time.perf_counter()
            done = subprocess.run(
                command, env={**_environ(), **env}, capture_output=True, text=True
            )
            runs[kind].append(time.perf_counter() - start)
            if done.returncode not in (0, 3):
                raise SystemExit(f"register-batch failed ({done.returncode}): {done.stderr}")
    ratios = [i / g for i, g in zip(runs["init"], runs["global"], strict=True)]
    seconds = {kind: float(np.median(values)) for kind, values in runs.items()}
    return {**seconds, "ratio": float(np.median(ratios)), "runs": runs}


def _environ() -> dict[str, str]:
    import os

    return dict(os.environ)


def table(records: list[dict], seconds: dict[str, float] | None) -> str:
    """The benchmark's table (Markdown)."""
    methods = ["byoc --init", "refinement only", "open3d", "open3d wide", "byoc global"]
    methods.append("byoc --init far")
    out = [
        f"{len(records)} pairs; right (wrong) against the ground truth, and in brackets against"
        " the truth refined on the data, on the pairs where the data determine it (the"
        f" refinements of the truth agree and at least {MIN_OVERLAP:.0%} of the source overlaps)",
        "",
        "| method | 5 deg / 10 cm | 2 deg / 5 cm | wrong with exit 0 | exit 3 | s / pair |",
        "|---|---|---|---|---|---|",
    ]
    for m in methods:
        rows = [r[m] for r in records]
        det = [r[m] for r in records if r["determined"]]

        def count(rows, d, c, key):
            return sum(within_errors(x[key], d, c) for x in rows)

        loose = f"{count(rows, 5, 0.10, 'gt')} ({count(det, 5, 0.10, 'refined')}/{len(det)})"
        tight = f"{count(rows, 2, 0.05, 'gt')} ({count(det, 2, 0.05, 'refined')}/{len(det)})"
        gated = [x for x in rows if x["passed"] is not None]
        wrong = sum(x["passed"] and not within_errors(x["gt"], 5, 0.10) for x in gated)
        wrong_det = sum(
            x["passed"] and not within_errors(x["refined"], 5, 0.10)
            for x in det
            if x["passed"] is not None
        )
        wrong = f"{wrong} ({wrong_det}/{len(det)})"
        refused = sum(not x["passed"] for x in gated)
        mean = np.mean([x["seconds"] for x in rows])
        gate = (str(wrong), str(refused)) if gated else ("-", "-")
        out.append(f"| {m} | {loose} | {tight} | {gate[0]} | {gate[1]} | {mean:.2f} |")
    out += ["", *bands(records)]
    if seconds:
        repeats = len(seconds["runs"]["init"])
        out += [
            "",
            f"register-batch on the same {len(records)} pairs, the median of {repeats} runs "
            f"each: {seconds['global']:.1f} s without the init column, {seconds['init']:.1f} s "
            f"with it (the median of the runs' ratios {seconds['ratio']:.2f})",
        ]
    return "\n".join(out)


#: the overlap bands of :func:`bands`: (low, high], share of the source
BANDS = ((0.3, 1.0), (0.1, 0.3), (0.0, 0.1))


def bands(records: list[dict]) -> list[str]:
    """Right results (refined truth, 5 deg / 10 cm) of the local and global paths per band of
    the clouds' overlap at the truth."""
    lines = []
    for low, high in BANDS:
        rows = [
            r for r in records if low < r["overlap"] <= high or (low == 0 and r["overlap"] == 0)
        ]
        right = {
            m: sum(within_errors(r[m]["refined"], 5, 0.10) for r in rows)
            for m in ("byoc --init", "byoc global")
        }
        lines.append(
            f"overlap ({low:.0%}, {high:.0%}]: {len(rows)} pairs, right: byoc --init "
            f"{right['byoc --init']}, byoc global {right['byoc global']}"
        )
    return lines


def within_errors(err, degrees: float, metres: float) -> bool:
    return err[0] < degrees and err[1] < metres


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = ["bench", "batch", "collect", "fit", "sweep"]
    parser.add_argument("command", nargs="?", default="bench", choices=commands)
    parser.add_argument("files", nargs="*", type=Path, help="fit: the collections")
    parser.add_argument("--out", type=Path, help="collect: the JSON Lines file")
    parser.add_argument("--pairs", type=int, default=28)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--near-deg", type=float, default=10.0)
    parser.add_argument("--near-m", type=float, default=0.30)
    parser.add_argument("--far-deg", type=float, default=40.0)
    parser.add_argument("--no-batch", action="store_true", help="skip the register-batch timing")
    parser.add_argument("--repeats", type=int, default=3, help="register-batch runs of each")
    parser.add_argument("--json", type=Path, help="bench: write the records here")
    args = parser.parse_args(argv)
    if args.command == "collect":
        if args.out is None:
            parser.error("collect needs --out")
        collect(args.out, args.seed)
        return 0
    if args.command == "fit":
        if not args.files:
            parser.error("fit needs collections")
        fit(args.files)
        return 0
    if args.command == "sweep":
        sweep(args)
        return 0
    if args.command == "batch":
        with tempfile.TemporaryDirectory(prefix="byoc-init-bench-") as folder:
            seconds = batch_times(batch_pairs(args), Path(folder), args.repeats)
        for kind in ("global", "init"):
            runs = ", ".join(f"{s:.1f}" for s in seconds["runs"][kind])
            print(f"{kind}: median {seconds[kind]:.1f} s ({runs})")
        runs = seconds["runs"]
        ratios = [i / g for i, g in zip(runs["init"], runs["global"], strict=True)]
        print(f"ratio: median {seconds['ratio']:.3f} ({', '.join(f'{r:.3f}' for r in ratios)})")
        return 0
    records, kept = run_pairs(args)
    seconds = None
    if not args.no_batch:
        with tempfile.TemporaryDirectory(prefix="byoc-init-bench-") as folder:
            seconds = batch_times(kept, Path(folder), args.repeats)
    if args.json:
        args.json.write_text(json.dumps({"records": records, "batch_s": seconds}))
    print(table(records, seconds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
