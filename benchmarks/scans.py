"""``byoc register-scans`` on the fragments of a TUM sequence, scored against their ground truth.

Usage::

    python benchmarks/scans.py [--data ../shared/data] [--sequence tum_fr1_desk_full] \
        [--out fr1_desk_bench] [--fragments DIR] [--frames-per-fragment 25] [--count 11] \
        [--features fpfh byoc] [--init-poses DEG,M [--seed N]] [--json results.json]

1. ``byoc make-fragments`` fuses the sequence into fragments of ``--frames-per-fragment``
   frames in ``OUT/fragments`` (TSDF fusion at the sequence's own poses; once: an earlier
   ``--out`` is reused), or ``--fragments DIR`` names the folder of an earlier
   ``make-fragments``; its ``make-fragments.json`` holds each fragment's ``T_world_cam``, the
   ground truth.
2. ``byoc register-scans`` places the first ``--count`` of them, once per ``--features``,
   each a separate process (whole-process wall and CPU seconds).
   With ``--init-poses DEG,M`` also once from initial poses (``--init-poses``, no features):
   the ground truth with each fragment turned by DEG degrees about a random axis through its
   centroid and shifted by M metres in a random direction (``--seed``), as a TUM file.
3. Each placed fragment's pose is compared with the ground truth, both in the first
   fragment's frame: rotation (degrees) and translation (cm) of ``inv(T_gt) T``; the table
   gives the median and largest of the errors, the pairs kept and the loop edges pruned.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_DATA = Path(
    os.environ.get("BYOC_SHARED_DATA", Path(__file__).parents[1] / "../shared/data")
)
FEATURES = ("fpfh", "byoc")


def _byoc(*args: str) -> tuple[float, float]:
    """Run ``byoc ARGS`` (this interpreter's package); ``(wall, CPU)`` seconds."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    command = [sys.executable, "-m", "byoc_cli.cli.main", *args]
    print("$ byoc " + " ".join(args), file=sys.stderr, flush=True)
    done = subprocess.run(command, stdout=subprocess.DEVNULL)
    if done.returncode not in (0, 3):  # 3: some scans not placed (the table says how many)
        raise subprocess.CalledProcessError(done.returncode, command)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return time.perf_counter() - start, cpu


def _rotation_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def pose_errors(folder: Path, truth: dict[str, np.ndarray]) -> list[tuple[float, float]]:
    """``(rotation deg, translation m)`` of every scan after the first of a ``register-scans``
    folder against ``truth`` (``T_world_cam`` per scan name); nan for a scan not placed."""
    report = json.loads((folder / "report.json").read_text())
    names = [Path(scan["path"]).stem for scan in report["scans"]]
    world = np.linalg.inv(truth[names[0]])
    errors = []
    for name in names[1:]:
        path = folder / "poses" / f"{name}.txt"
        if not path.exists():
            errors.append((float("nan"), float("nan")))
            continue
        D = np.linalg.inv(world @ truth[name]) @ np.loadtxt(path)
        errors.append((_rotation_deg(D[:3, :3]), float(np.linalg.norm(D[:3, 3]))))
    return errors


def perturbed_poses(clouds: list[str], truth: list, degrees: float, metres: float, seed: int):
    """``truth`` (``T_world_cam`` per cloud), each turned by ``degrees`` about a random axis
    through its cloud's centroid and shifted by ``metres`` in a random direction."""
    from byoc_cli.io import read_point_cloud

    rng = np.random.default_rng(seed)
    out = []
    for path, pose in zip(clouds, truth, strict=True):
        centre = pose[:3, :3] @ read_point_cloud(path).points.mean(axis=0) + pose[:3, 3]
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        a = np.radians(degrees)
        move = np.eye(4)
        move[:3, :3] = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
        step = rng.normal(size=3)
        move[:3, 3] = centre - move[:3, :3] @ centre + metres * step / np.linalg.norm(step)
        out.append(move @ pose)
    return out


def _arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--sequence", default="tum_fr1_desk_full")
    parser.add_argument("--out", type=Path, default=Path("scans_bench"))
    parser.add_argument("--fragments", type=Path, help="an earlier make-fragments folder")
    parser.add_argument("--frames-per-fragment", type=int, default=25)
    parser.add_argument("--count", type=int, default=11)
    parser.add_argument("--features", nargs="+", default=list(FEATURES))
    parser.add_argument("--init-poses", help="DEG,M: also from the ground truth this far off")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    unknown = [f for f in args.features if f not in FEATURES]
    if unknown:
        parser.error(f"--features {unknown[0]!r}: one of {', '.join(FEATURES)}")
    if not (args.data / "rgbd" / args.sequence).is_dir():
        parser.error(f"--data {args.data}: no rgbd/{args.sequence} folder")
    if args.fragments is not None and not (args.fragments / "make-fragments.json").is_file():
        parser.error(f"--fragments {args.fragments}: no make-fragments.json")
    if args.count < 2 or args.frames_per_fragment < 1:
        parser.error("--count must be >= 2 and --frames-per-fragment >= 1")
    return args


def main() -> None:
    args = _arguments()
    fragments = args.fragments or args.out / "fragments"
    manifest_path = fragments / "make-fragments.json"
    if not manifest_path.exists():
        _byoc(
            "make-fragments", "--rgbd-dir", str(args.data / "rgbd" / args.sequence),
            "--out", str(fragments), "--frames-per-fragment", str(args.frames_per_fragment),
        )  # fmt: skip
    manifest = json.loads(manifest_path.read_text())
    truth = {f"cloud_bin_{f['index']}": np.asarray(f["T_world_cam"]) for f in manifest["fragments"]}
    clouds = [str(fragments / args.sequence / f"cloud_bin_{k}.ply") for k in range(args.count)]
    runs = [(features, ["--features", features]) for features in args.features]
    if args.init_poses:
        from byoc_cli.io.trajectory import format_tum_trajectory

        degrees, metres = (float(v) for v in args.init_poses.split(","))
        poses = [truth[f"cloud_bin_{k}"] for k in range(args.count)]
        init = args.out / "init_poses.txt"
        init.parent.mkdir(parents=True, exist_ok=True)
        guess = perturbed_poses(clouds, poses, degrees, metres, args.seed)
        init.write_text(format_tum_trajectory(list(range(args.count)), guess))
        runs.append((f"init {degrees:g} deg, {100 * metres:g} cm", ["--init-poses", str(init)]))
    rows = []
    for features, options in runs:
        folder = args.out / f"scans-{features.split()[0]}"
        shutil.rmtree(folder, ignore_errors=True)
        wall, cpu = _byoc("register-scans", *clouds, "--out", str(folder), *options)
        report = json.loads((folder / "report.json").read_text())
        e = np.asarray(pose_errors(folder, truth))
        rows.append(
            {
                "features": features,
                "placed": report["num_placed"],
                "scans": report["num_scans"],
                "pairs_kept": report["pairs_kept"],
                "pairs_tried": report["pairs_tried"],
                "edges_pruned": report["edges_pruned"],
                "median_rotation_deg": float(np.nanmedian(e[:, 0])),
                "median_translation_cm": 100 * float(np.nanmedian(e[:, 1])),
                "max_rotation_deg": float(np.nanmax(e[:, 0])),
                "max_translation_cm": 100 * float(np.nanmax(e[:, 1])),
                "wall_s": wall,
                "cpu_s": cpu,
            }
        )
    print(
        "| features | placed | pairs kept / tried | pruned | median error | max error "
        "| wall s (CPU s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['features']} | {r['placed']} of {r['scans']} | {r['pairs_kept']} / "
            f"{r['pairs_tried']} | {r['edges_pruned']} | {r['median_rotation_deg']:.1f} deg, "
            f"{r['median_translation_cm']:.1f} cm | {r['max_rotation_deg']:.1f} deg, "
            f"{r['max_translation_cm']:.1f} cm | {r['wall_s']:.0f} ({r['cpu_s']:.0f}) |"
        )
    if args.json:
        args.json.write_text(json.dumps({"sequence": args.sequence, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
