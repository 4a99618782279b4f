"""Low-overlap pairs cut from real fragment pairs, and what a register-batch summary got on them.

Issue 35 describes the default's wrong results with exit 0 on real 3DLoMatch pairs: half of
them have the rotation right and the translation slid 1.2 to 2 m along kitchen cabinets. The
development fragments of docs/low-overlap.md (a desk, a box-shaped cabinet) fail otherwise
(turned boxes). ``make`` cuts the pairs of a 3DMatch-layout benchmark (``gt.log``; the shared
sample's three redkitchen pairs) with planes into pairs of a chosen overlap: for each cut a
seeded random direction ``d``, the source (moved by the ground truth) keeping what lies beyond
``m - w`` along ``d`` and the target what lies before ``m + w`` (``m`` the median of both),
``w`` bisected until the share of kept source points within 3.75 cm of a kept target point
(3DLoMatch's overlap) reaches a goal drawn from the band (a cut whose measured overlap ends
more than 0.03 from its goal is drawn again). With ``--view`` each cloud is cut by the
directions its own sensor looked along instead (each fragment in its first camera's frame):
the source keeps the points whose viewing direction from the source's camera makes a cosine
above ``m - w`` with ``d``, the target those below ``m + w`` from its own; a cut takes whole
rays away, so nothing that a sensor saw through is left looking empty (what the visibility
check of ``register`` reads; a planar cut takes away surfaces in front of others that stay).
Each pair is written as
``NAME/source.ply``, ``target.ply`` (the kept points, in each fragment's own frame),
``T_gt.txt`` and ``info.json``, with ``pairs.txt`` for ``byoc register-batch``.

``judge`` scores a summary of ``register-batch`` on them: right when the RMSE of the source's
points under ``T`` against ``T_gt`` is at most 0.2 m (3DMatch's registration recall) and the
rotation is within 5 deg (issue 35's count); a wrong result is *slid* when its rotation is
within 5 deg and its source centroid 0.5 m or more away.

``turn`` gives the pairs of a cut set the relative rotations of real low-overlap pairs: for
each pair a rotation ``Q`` drawn (seeded) from the ground truth of a 3DMatch-layout benchmark
(``gt.log`` of every scene under ``--gt-dir``; 3DLoMatch's 1781 pairs: median 52 deg, 42 %
above 60 deg, where the cut pairs' own are 13 to 40 deg), the source turned about its origin
(its sensor stays there) by ``R = Q^T R_gt`` so that the pair's rotation becomes ``Q``; the
translation of the truth is unchanged. ``info.json`` adds ``turned_deg`` (the angle of
``Q``).

Usage:
    python benchmarks/cut_pairs.py make --fragments ../shared/data/3dmatch/sample/3DMatch \\
        --out cut --per-pair 16 --seed 0
    cd cut && byoc register-batch pairs.txt --summary summary.jsonl
    python benchmarks/cut_pairs.py judge cut/summary.jsonl [--pairs]
    python benchmarks/cut_pairs.py turn cut --out cut-turned --seed 0 \\
        --gt-dir ../shared/data/3dmatch/benchmarks/3DLoMatch
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

#: 3DLoMatch's overlap: a point within this of the other cloud (metres)
OVERLAP_RADIUS = 0.0375
#: right: RMSE of the source's points at most this (metres) and rotation within DEG
RMSE = 0.2
DEG = 5.0
#: a wrong result within DEG whose source centroid moved at least this far (metres) is slid
SLID = 0.5
#: each cut keeps at least this share of each cloud, and its overlap within TOLERANCE of the goal
MIN_KEPT = 0.2
TOLERANCE = 0.03


def cut(
    moved: np.ndarray,
    target: np.ndarray,
    nearest: np.ndarray,
    direction: np.ndarray,
    goal: float,
    sensors: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """One cut of a pair to an overlap ``goal``: planar, or by viewing directions.

    Args:
        moved: ``(N, 3)`` source points moved into the target's frame by the ground truth.
        target: ``(M, 3)`` target points.
        nearest: ``(N,)`` index of each source point's nearest target point within
            :data:`OVERLAP_RADIUS`, -1 where none.
        direction: ``(3,)`` unit vector along which the pair is cut.
        goal: the overlap to reach.
        sensors: ``(source, target)`` sensor positions ``(3,)`` in the target's frame: cut by
            the cosine of each point's viewing direction with ``direction``; None: planar.

    Returns:
        ``(keep_source (N,), keep_target (M,), overlap)`` boolean masks and the overlap reached,
        or None when no cut keeps :data:`MIN_KEPT` of each cloud within :data:`TOLERANCE`.
    """
    if sensors is None:
        along_src, along_tgt = moved @ direction, target @ direction
    else:
        along_src, along_tgt = (
            _unit(points - at) @ direction
            for points, at in zip((moved, target), sensors, strict=True)
        )
    middle = float(np.median(np.concatenate([along_src, along_tgt])))
    low, high = 0.0, float(np.ptp(np.concatenate([along_src, along_tgt])))
    found = None
    for _ in range(30):
        width = (low + high) / 2
        keep_src, keep_tgt = along_src > middle - width, along_tgt < middle + width
        hit = nearest[keep_src]
        overlap = float(np.mean((hit >= 0) & keep_tgt[np.maximum(hit, 0)])) if hit.size else 0.0
        if overlap < goal:
            low = width
        else:
            high = width
        found = keep_src, keep_tgt, overlap
    keep_src, keep_tgt, overlap = found
    if keep_src.mean() < MIN_KEPT or keep_tgt.mean() < MIN_KEPT:
        return None
    # the nearest target point may be cut away where another within the radius is kept: the
    # bisection's overlap is a lower bound, the kept clouds' is measured
    overlap = overlap_of(moved[keep_src], target[keep_tgt])
    return (keep_src, keep_tgt, overlap) if abs(overlap - goal) <= TOLERANCE else None


def _unit(vectors: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(vectors, axis=1, keepdims=True)
    return vectors / np.maximum(norm, 1e-12)


def overlap_of(moved: np.ndarray, target: np.ndarray) -> float:
    """The share of ``moved (N, 3)`` within :data:`OVERLAP_RADIUS` of ``target (M, 3)``."""
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(target).query(moved, distance_upper_bound=OVERLAP_RADIUS)
    return float(np.mean(np.isfinite(distance)))


def make(
    fragments: Path,
    out: Path,
    per_pair: int,
    seed: int,
    band: tuple[float, float],
    view: bool = False,
) -> int:
    """Write ``per_pair`` cuts of every ground-truth pair under ``fragments`` (``view``: by
    viewing directions); how many."""
    from scipy.spatial import cKDTree

    from byoc_cli.api import load_cloud
    from byoc_cli.evaluation.benchmark import load_benchmark_pairs
    from byoc_cli.io import write_ply
    from byoc_cli.io.threedmatch import discover_benchmark

    rng = np.random.default_rng(seed)
    lines = []
    for pair in load_benchmark_pairs(discover_benchmark(fragments)).pairs:
        source = load_cloud(pair.source, scale=1.0).astype(np.float64)
        target = load_cloud(pair.target, scale=1.0).astype(np.float64)
        moved = source @ pair.T_gt[:3, :3].T + pair.T_gt[:3, 3]
        distance, nearest = cKDTree(target).query(moved, distance_upper_bound=OVERLAP_RADIUS)
        nearest = np.where(np.isfinite(distance), nearest, -1)
        made = 0
        for _ in range(50 * per_pair):
            if made == per_pair:
                break
            direction = rng.standard_normal(3)
            direction /= np.linalg.norm(direction)
            sensors = (pair.T_gt[:3, 3], np.zeros(3)) if view else None
            found = cut(moved, target, nearest, direction, float(rng.uniform(*band)), sensors)
            if found is None:
                continue
            keep_src, keep_tgt, overlap = found
            name = f"{pair.scene}-{pair.j}-{pair.i}-{made}"
            folder = out / name
            folder.mkdir(parents=True, exist_ok=True)
            write_ply(folder / "source.ply", source[keep_src].astype(np.float32))
            write_ply(folder / "target.ply", target[keep_tgt].astype(np.float32))
            np.savetxt(folder / "T_gt.txt", pair.T_gt)
            info = {
                "scene": pair.scene,
                "source_fragment": pair.j,
                "target_fragment": pair.i,
                "overlap": overlap,
                "direction": direction.tolist(),
                "cut": "view" if view else "plane",
                "kept": [int(keep_src.sum()), int(keep_tgt.sum())],
            }
            (folder / "info.json").write_text(json.dumps(info, indent=1) + "\n")
            lines.append(f"{name}/source.ply {name}/target.ply out/{name}.txt")
            made += 1
            print(f"{name}: overlap {overlap:.3f}", file=sys.stderr, flush=True)
    (out / "out").mkdir(parents=True, exist_ok=True)
    (out / "pairs.txt").write_text("\n".join(lines) + "\n")
    return len(lines)


def judged(record: dict, root: Path) -> dict:
    """One summary record scored against its folder's ``T_gt.txt``: ``right``, ``slid``,
    ``rmse`` (m), ``rotation`` (deg), ``moved`` (m, the source centroid), ``passed``."""
    from byoc_cli.api import load_cloud

    folder = (root / record["source"]).parent
    T_gt = np.loadtxt(folder / "T_gt.txt")
    info = json.loads((folder / "info.json").read_text())
    out = {"name": folder.name, "overlap": info["overlap"], "passed": bool(record.get("passed"))}
    out["confidence"] = record.get("confidence")
    if record.get("T_tgt_src") is None:
        return {**out, "right": False, "slid": False, "rmse": None, "rotation": None, "moved": None}
    T = np.asarray(record["T_tgt_src"], dtype=np.float64)
    points = load_cloud(folder / "source.ply", scale=1.0).astype(np.float64)
    gap = (points @ (T - T_gt)[:3, :3].T) + (T - T_gt)[:3, 3]
    rmse = float(np.sqrt(np.mean(np.sum(gap**2, axis=1))))
    cos = (np.trace(T[:3, :3] @ T_gt[:3, :3].T) - 1.0) / 2.0
    rotation = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
    moved = float(np.linalg.norm(gap.mean(axis=0)))
    right = rmse <= RMSE and rotation < DEG
    slid = not right and rotation < DEG and moved >= SLID
    return {**out, "right": right, "slid": slid, "rmse": rmse, "rotation": rotation, "moved": moved}


def judge(summary: Path, show_pairs: bool) -> list[str]:
    """The lines ``judge`` prints for ``summary``: each pair's with ``show_pairs``, then the
    totals."""
    records = [json.loads(line) for line in summary.read_text().splitlines() if line.strip()]
    scored = [judged(r, summary.parent) for r in records]
    lines = []
    if show_pairs:
        for s in scored:
            verdict = "right" if s["right"] else ("slid" if s["slid"] else "wrong")
            exit_code = "exit 0" if s["passed"] else "refused"
            numbers = (
                "no T"
                if s["rmse"] is None
                else f"rmse {s['rmse']:.3f} m rot {s['rotation']:.1f} deg moved {s['moved']:.2f} m"
            )
            confidence = s["confidence"] if s["confidence"] is not None else float("nan")
            lines.append(
                f"{s['name']} overlap {s['overlap']:.2f} {verdict} {exit_code} "
                f"confidence {confidence:.2f} {numbers}"
            )
    rr = sum(s["rmse"] is not None and s["rmse"] <= RMSE for s in scored)
    right0 = sum(s["right"] and s["passed"] for s in scored)
    wrong0 = [s for s in scored if s["passed"] and not s["right"]]
    refused = sum(not s["passed"] for s in scored)
    lines.append(
        f"pairs {len(scored)} RR {100 * rr / max(len(scored), 1):.1f} % right_exit0 {right0} "
        f"wrong_exit0 {len(wrong0)} (slid {sum(s['slid'] for s in wrong0)}) refused {refused}"
    )
    return lines


def benchmark_rotations(gt_dir: Path) -> np.ndarray:
    """``(P, 3, 3)`` the rotations of every pair in the ``gt.log`` files under ``gt_dir``."""
    from byoc_cli.errors import InputError
    from byoc_cli.io.threedmatch import read_gt_log

    rotations = [
        record.T_tgt_src[:3, :3]
        for log in sorted(gt_dir.rglob("gt.log"))
        for record in read_gt_log(log)
    ]
    if not rotations:
        raise InputError(gt_dir, "no gt.log with a pair under it")
    return np.stack(rotations)


def turn(cut_set: Path, out: Path, seed: int, gt_dir: Path) -> int:
    """Write the pairs of ``cut_set`` (a folder of :func:`make`) to ``out`` with each source
    turned so that the pair's rotation is one drawn from ``gt_dir``'s; how many."""
    from byoc_cli.api import load_cloud
    from byoc_cli.errors import InputError
    from byoc_cli.io import write_ply

    listed = cut_set / "pairs.txt"
    if not listed.is_file():
        raise InputError(listed, "no such file (a folder made by cut_pairs.py make)")
    rotations = benchmark_rotations(gt_dir)
    rng = np.random.default_rng(seed)
    lines = []
    for line in listed.read_text().split("\n"):
        if not line.strip():
            continue
        name = line.split()[0].split("/")[0]
        T_gt = np.loadtxt(cut_set / name / "T_gt.txt")
        Q = rotations[rng.integers(len(rotations))]
        R = Q.T @ T_gt[:3, :3]  # the new truth's rotation, T_gt's R R^T, is Q
        folder = out / name
        folder.mkdir(parents=True, exist_ok=True)
        source = load_cloud(cut_set / name / "source.ply", scale=1.0).astype(np.float64)
        write_ply(folder / "source.ply", (source @ R.T).astype(np.float32))
        target = load_cloud(cut_set / name / "target.ply", scale=1.0)
        write_ply(folder / "target.ply", target.astype(np.float32))
        truth = T_gt.copy()
        truth[:3, :3] = Q
        np.savetxt(folder / "T_gt.txt", truth)
        info = json.loads((cut_set / name / "info.json").read_text())
        cosine = (np.trace(Q) - 1.0) / 2.0
        info["turned_deg"] = math.degrees(math.acos(min(1.0, max(-1.0, cosine))))
        (folder / "info.json").write_text(json.dumps(info, indent=1) + "\n")
        lines.append(line)
    (out / "out").mkdir(parents=True, exist_ok=True)
    (out / "pairs.txt").write_text("\n".join(lines) + "\n")
    return len(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("make")
    p.add_argument("--fragments", type=Path, required=True, help="a 3DMatch-layout benchmark")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--per-pair", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--band", type=float, nargs=2, default=(0.1, 0.3), metavar=("LOW", "HIGH"))
    p.add_argument("--view", action="store_true", help="cut by each sensor's viewing directions")
    p = sub.add_parser("turn")
    p.add_argument("cut_set", type=Path, help="a folder written by make")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--gt-dir", type=Path, required=True, help="gt.log files to draw from")
    p = sub.add_parser("judge")
    p.add_argument("summary", type=Path)
    p.add_argument("--pairs", action="store_true", help="a line per pair too")
    args = parser.parse_args()
    from byoc_cli.errors import InputError

    try:
        if args.command == "make":
            if not 0.0 < args.band[0] < args.band[1] < 1.0 or args.per_pair < 1:
                parser.error("--band LOW HIGH: 0 < LOW < HIGH < 1; --per-pair at least 1")
            made = make(args.fragments, args.out, args.per_pair, args.seed, args.band, args.view)
            print(f"{made} pairs")
        elif args.command == "turn":
            print(f"{turn(args.cut_set, args.out, args.seed, args.gt_dir)} pairs")
        else:
            if not args.summary.is_file():
                parser.error(f"{args.summary}: no such file")
            print("\n".join(judge(args.summary, args.pairs)))
    except InputError as err:
        parser.error(str(err))
    return 0


if __name__ == "__main__":
    sys.exit(main())
