"""`byoc register-batch` (no flags) on laser scans of small objects against Open3D's FPFH + RANSAC
at a hand-set voxel, each in one process, as issue 33 measures them.

Three steps:

* ``make --out DIR``: simulated pairs of free-form objects (benchmarks/_scan_sim_shapes.py:
  ``--shapes`` x ``--views`` x ``--angles`` x ``--seeds``, ``--sizes`` in turn (10, 20 and
  30 cm), ``--noise`` of range (0.1 mm), ``--outliers`` share of returns off the surface (0)),
  each ``DIR/<name>/{source.ply,target.ply,T_gt.txt,info.json}``, and ``DIR/pairs.txt``
  (``source target out/<name>.txt``). ``info.json``'s ``voxel`` is the hand-set voxel
  (size / 50).
* ``make-tabletop --out DIR``: the same layout of the fused tabletop box of
  benchmarks/scan_sim.py (``object_pair``, its table cut off) at ``--sizes`` x ``--angles``
  (20 to 80 deg): a scanned object with edges, where the learned features go first.
* ``scale SRC --out DIR --factor 1000``: the pair folders of ``SRC`` in other units (the
  points, the truth's translation, ``info.json``'s size and voxel times the factor; float32
  PLY): objects in millimetres, which by size alone look like scenes 100 m across.
* ``run DIR``: ``--repeats`` times, interleaved: ``byoc register-batch DIR/pairs.txt
  --overwrite`` (plus ``--byoc-args``) and the Open3D loop (``o3d-loop``: every pair of the list
  through benchmarks/o3d_fpfh_ransac.py's pipeline at ``info.json``'s voxel, in one
  process), each under ``/usr/bin/time -v``; prints per repeat and as medians: registered
  (byoc: right and passed the gate; Open3D: right), wrong with exit 0 (byoc: passed, not
  right; Open3D: not right), refused (byoc), CPU seconds (user + sys), peak RSS, and the CPU
  ratio. ``--baseline SRC`` adds ``byoc`` of another source tree (``PYTHONPATH=SRC``).
* ``cues [GROUP=DIR ...]``: the share of rough neighbourhoods of each pair's clouds at its
  auto voxel (what ``byoc`` reads to start a pair with FPFH: pipeline/feature_choice.py), on
  the shared data's pairs where the learned features win (the demo pair, the 3DMatch sample,
  depth-frame pairs) and on the pair folders given; the range per group.
* ``judge SUMMARY.jsonl``: one line per pair of a ``register-batch`` summary: rotation and
  translation error (share of the size, and cm), confidence, passed, right, fallback,
  seconds per stage.

Right: rotation within 5 deg and translation within 10 % of the object's size (``info.json``;
the simulated rooms of benchmarks/scan_sim.py's ``room`` set, whose ``pairs.txt`` it writes,
are judged alike, their size the room's longest side).

Usage: python benchmarks/objects.py make --out DIR [--shapes blob torus ...] [--views ...]
           [--angles 30 60] [--seeds 0 1] [--sizes 0.1 0.2 0.3] [--noise 1e-4] [--outliers 0.02]
       python benchmarks/objects.py make-tabletop --out DIR [--cache C]
       python benchmarks/objects.py scale SRC --out DIR [--factor 1000]
       python benchmarks/objects.py run DIR [--repeats 3] [--baseline ../main/src]
           [--byoc-args "--fallback none"]
       python benchmarks/objects.py cues [objects=DIR street=DIR2 ...] [--no-reference]
       python benchmarks/objects.py judge DIR/summary.jsonl
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MAX_ROT_DEG = 5.0
MAX_TRANS_SHARE = 0.10  # of the object's size
SIZES = (0.1, 0.2, 0.3)


def errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """Rotation (deg) and translation (units of T) of ``inv(T) @ T_gt``."""
    D = np.linalg.inv(T) @ T_gt
    cos = np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(D[:3, 3]))


_CENTRES: dict[Path, np.ndarray] = {}


def _centre(folder: Path) -> np.ndarray:
    """The median point of the pair's source (the object, far from the scanner's origin)."""
    if folder not in _CENTRES:
        from plyfile import PlyData

        v = PlyData.read(str(folder / "source.ply"))["vertex"]
        _CENTRES[folder] = np.median(np.stack([v["x"], v["y"], v["z"]], axis=1), axis=0)
    return _CENTRES[folder]


def right(T: np.ndarray, folder: Path) -> tuple[bool, float, float]:
    """Whether ``T`` is right for the pair in ``folder``, and its errors: rotation (deg) and
    how far it puts the source's median point from where the truth does (share of the size:
    the translation at the scanner's origin, three sizes away, would count the rotation's
    error again)."""
    info = json.loads((folder / "info.json").read_text())
    T_gt = np.loadtxt(folder / "T_gt.txt")
    rot, _ = errors(T, T_gt)
    c = _centre(folder)
    size = info.get("size", info.get("scene_size_m"))  # scan_sim.py's object pairs: the latter
    share = float(np.linalg.norm((T - T_gt)[:3, :3] @ c + (T - T_gt)[:3, 3])) / size
    return rot < MAX_ROT_DEG and share < MAX_TRANS_SHARE, rot, share


def _pairs(pairs: Path) -> list[tuple[Path, Path, Path]]:
    """``(source, target, output)`` of each line of a pair list, relative to its folder."""
    out = []
    for line in pairs.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            s, t, o = line.split()
            out.append(tuple(pairs.parent / p for p in (s, t, o)))
    return out


def make(args: argparse.Namespace) -> None:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from _scan_sim_shapes import shape_pair
    from _scan_sim_write import write_pair

    lines, k = [], 0
    for kind in args.shapes:
        for view in args.views:
            for angle in args.angles:
                for seed in args.seeds:
                    size = args.sizes[k % len(args.sizes)]
                    k += 1
                    name = f"{kind}-{view}-{angle:g}-s{seed}"
                    pair = shape_pair(kind, angle, size, view, noise=args.noise, seed=seed,
                                      outliers=args.outliers)  # fmt: skip
                    info = {"kind": "shape", "shape": kind, "view": view, "angle_deg": angle,
                            "seed": seed, "size": size, "voxel": size / 50,
                            "noise": args.noise, "outliers": args.outliers}  # fmt: skip
                    write_pair(args.out / name, pair, info)
                    lines.append(f"{name}/source.ply {name}/target.ply out/{name}.txt")
                    print(f"{name}: {len(pair[0])} + {len(pair[1])} points", file=sys.stderr)
    (args.out / "pairs.txt").write_text("\n".join(lines) + "\n")
    (args.out / "out").mkdir(exist_ok=True)


def make_tabletop(args: argparse.Namespace) -> None:
    """The fused tabletop box (`scan_sim.object_pair`, its table cut off) at each size and
    angle: rays size / 400 apart, range noise size / 2000 (0.1 mm at 20 cm)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from _scan_sim_object import object_pair
    from _scan_sim_write import write_pair

    lines = []
    for size in args.sizes:
        for angle in args.angles:
            name = f"obj-{size:g}m-{angle:g}deg"
            pair = object_pair(angle, size * 2.5e-3, size, size * 5e-4, cache=args.cache)
            info = {"kind": "object", "angle_deg": angle, "size": size, "voxel": size / 50}
            write_pair(args.out / name, pair, info)
            lines.append(f"{name}/source.ply {name}/target.ply out/{name}.txt")
            print(f"{name}: {len(pair[0])} + {len(pair[1])} points", file=sys.stderr)
    (args.out / "pairs.txt").write_text("\n".join(lines) + "\n")
    (args.out / "out").mkdir(exist_ok=True)


def scale(args: argparse.Namespace) -> None:
    """The pair folders of ``args.src`` (and its ``pairs.txt``) times ``args.factor`` in
    ``args.out``."""
    from plyfile import PlyData, PlyElement

    folders = sorted(p.parent for p in args.src.glob("*/info.json"))
    for folder in folders:
        out = args.out / folder.name
        out.mkdir(parents=True, exist_ok=True)
        for name in ("source.ply", "target.ply"):
            v = PlyData.read(str(folder / name))["vertex"]
            points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
            rows = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
            rows["x"], rows["y"], rows["z"] = (points * args.factor).T
            PlyData([PlyElement.describe(rows, "vertex")]).write(str(out / name))
        T = np.loadtxt(folder / "T_gt.txt")
        T[:3, 3] *= args.factor
        np.savetxt(out / "T_gt.txt", T, fmt="%.17g")
        info = json.loads((folder / "info.json").read_text())
        info.update(size=info["size"] * args.factor, voxel=info["voxel"] * args.factor)
        (out / "info.json").write_text(json.dumps(info, indent=1))
    (args.out / "out").mkdir(exist_ok=True)
    (args.out / "pairs.txt").write_text((args.src / "pairs.txt").read_text())
    print(f"{len(folders)} pairs times {args.factor:g} in {args.out}")


def o3d_loop(args: argparse.Namespace) -> None:
    """Every pair of the list through Open3D's FPFH + RANSAC at its hand-set voxel, in this
    process; T files as ``--out-dir/<name>.txt``."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from byoc_cli.api import load_cloud
    from o3d_fpfh_ransac import fpfh_ransac

    args.out_dir.mkdir(parents=True, exist_ok=True)
    for src, tgt, out in _pairs(args.pairs):
        voxel = json.loads((src.parent / "info.json").read_text())["voxel"]
        T, _ = fpfh_ransac(load_cloud(src, scale=1.0), load_cloud(tgt, scale=1.0), voxel)
        np.savetxt(args.out_dir / out.name, T, fmt="%.17g")


def _timed(command: list[str], env: dict | None = None) -> dict:
    """CPU seconds (user + sys), wall seconds and peak RSS (MB) of ``command`` under
    ``/usr/bin/time -v``."""
    run = subprocess.run(
        ["/usr/bin/time", "-v", *command], capture_output=True, text=True, env=env, check=False
    )
    if run.returncode not in (0, 3):
        raise SystemExit(f"{shlex.join(command)} failed ({run.returncode}):\n{run.stderr[-3000:]}")

    def field(name: str) -> float:
        return float(re.search(rf"{name}: ([\d.:]+)", run.stderr).group(1).split(":")[-1])

    cpu = field(r"User time \(seconds\)") + field(r"System time \(seconds\)")
    return {"cpu": cpu, "rss_mb": field(r"Maximum resident set size \(kbytes\)") / 1024}


def _count_byoc(summary: Path) -> dict:
    counts = {"registered": 0, "wrong_exit0": 0, "refused": 0}
    for line in summary.read_text().splitlines():
        r = json.loads(line)
        if r["status"] == "error" or r.get("T_tgt_src") is None:
            counts["refused"] += 1
            continue
        ok, _, _ = right(np.array(r["T_tgt_src"]), (summary.parent / r["source"]).parent)
        if not r["passed"]:
            counts["refused"] += 1
        elif ok:
            counts["registered"] += 1
        else:
            counts["wrong_exit0"] += 1
    return counts


def _count_o3d(pairs: Path, out_dir: Path) -> dict:
    ok = [right(np.loadtxt(out_dir / o.name), s.parent)[0] for s, _, o in _pairs(pairs)]
    return {"registered": sum(ok), "wrong_exit0": len(ok) - sum(ok), "refused": 0}


def run(args: argparse.Namespace) -> None:
    pairs = args.dir.resolve() / "pairs.txt"  # the summary's paths are read from elsewhere
    trees = {"byoc": str(ROOT / "src")}
    if args.baseline:
        trees["baseline"] = str(Path(args.baseline).resolve())
    rows: dict[str, list[dict]] = {name: [] for name in [*trees, "open3d"]}
    (args.dir / "out").mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            for name, src in trees.items():
                env = {**os.environ, "PYTHONPATH": src}
                summary = Path(tmp) / f"{name}-{repeat}.jsonl"
                command = [sys.executable, "-m", "byoc_cli.cli.main", "register-batch",
                           str(pairs), "--overwrite", "-q", "--summary", str(summary),
                           *shlex.split(args.byoc_args)]  # fmt: skip
                row = {**_timed(command, env), **_count_byoc(summary)}
                rows[name].append(row)
                print(f"repeat {repeat} {name:8s} {row}", file=sys.stderr)
            out = Path(tmp) / f"o3d-{repeat}"
            command = [sys.executable, __file__, "o3d-loop", str(pairs), "--out-dir", str(out)]
            row = {**_timed(command), **_count_o3d(pairs, out)}
            rows["open3d"].append(row)
            print(f"repeat {repeat} open3d   {row}", file=sys.stderr)
    n = len(_pairs(pairs))
    print(f"{n} pairs, medians of {args.repeats} repeats")
    med = {k: {f: statistics.median(r[f] for r in v) for f in v[0]} for k, v in rows.items()}
    for name, m in med.items():
        ratio = m["cpu"] / med["open3d"]["cpu"]
        print(
            f"{name:8s} registered {m['registered']:4.0f}  wrong exit 0 {m['wrong_exit0']:3.0f}  "
            f"refused {m['refused']:3.0f}  CPU {m['cpu']:7.2f} s ({m['cpu'] / n:5.2f} per pair, "
            f"{ratio:4.2f}x Open3D)  peak RSS {m['rss_mb']:6.0f} MB"
        )


def _reference_pairs():
    """``(group, name, src, tgt)`` of the shared data where the learned features win: the demo
    pair, the 3DMatch sample's pairs, depth-frame pairs of TUM fr1_desk, fr1_xyz, fr3_cabinet
    and the RealSense tabletop."""
    from byoc_cli.api import load_cloud

    data = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
    demo = data / "pairs" / "3dmatch_demo"
    yield "3dmatch", "demo", load_cloud(demo / "source.ply"), load_cloud(demo / "target.ply")
    sample = data / "3dmatch" / "sample" / "3DMatch"
    for scene in sorted(p for p in sample.iterdir() if p.is_dir() and "-eval" not in p.name):
        log = (sample / f"{scene.name}-evaluation" / "gt.log").read_text().split("\n")
        for k in range(0, len(log) - 1, 5):
            i, j, _ = log[k].split()
            clouds = [load_cloud(scene / f"cloud_bin_{n}.ply") for n in (j, i)]
            yield "3dmatch", f"{scene.name}_{i}_{j}", *clouds
    for seq, step, scale in (("tum_fr1_desk", 3, 5000), ("tum_fr1_xyz", 4, 5000),
                             ("tum_fr3_cabinet", 10, 5000)):  # fmt: skip
        root = data / "rgbd" / seq
        frames = sorted((root / "depth").glob("*.png"))
        for a in range(0, min(len(frames) - step, 3 * step), step):
            clouds = [load_cloud(frames[a + d], intrinsics=root / "intrinsics.json",
                                 depth_scale=scale) for d in (0, step)]  # fmt: skip
            yield "depth frames", f"{seq}_{a}", *clouds
    root = data / "rgbd" / "realsense_tabletop"
    frames = sorted((root / "seq-01").glob("*.depth.png"))
    for a in (0, 15, 30):
        clouds = [load_cloud(frames[a + d], intrinsics=root / "camera-intrinsics.txt",
                             depth_scale=1000) for d in (0, 8)]  # fmt: skip
        yield "depth frames", f"realsense_tabletop_{a}", *clouds


def cues(args: argparse.Namespace) -> None:
    """The rough shares of each pair's clouds at its auto voxel (what the feature choice
    reads), per group: the reference pairs and the pair folders given."""
    import torch

    from byoc_cli.api import load_cloud
    from byoc_cli.geometry.sampling import rough_share
    from byoc_cli.pipeline.feature_choice import SMOOTH_SHARE
    from byoc_cli.pipeline.scale import choose_voxel, measure

    def given():
        for group in args.pairs:
            label, _, folder = group.partition("=")
            for pair in sorted(Path(folder).glob("*/source.ply")):
                clouds = [
                    load_cloud(pair.parent / f, scale=1.0) for f in ("source.ply", "target.ply")
                ]
                yield label, pair.parent.name, *clouds

    groups: dict[str, list[float]] = {}
    sources = given() if args.no_reference else (*_reference_pairs(), *given())
    for group, name, src, tgt in sources:
        scales = [measure(torch.from_numpy(c), n) for c, n in ((src, "s"), (tgt, "t"))]
        voxel = choose_voxel(tuple(scales), 0.025).voxel_size
        rough = [rough_share(torch.from_numpy(c), voxel) for c in (src, tgt)]
        groups.setdefault(group, []).extend(rough)
        fires = "FPFH first" if max(rough) <= SMOOTH_SHARE else ""
        print(f"{group:14s} {name:34s} rough {rough[0]:.3f} {rough[1]:.3f} {fires}")
    print(f"rough share of the clouds, per group (FPFH first when both are <= {SMOOTH_SHARE})")
    for group, values in groups.items():
        print(f"  {group:14s} {len(values):3d} clouds  {min(values):.3f} .. {max(values):.3f}")


def judge(args: argparse.Namespace) -> None:
    right_refused = 0
    for line in args.summary.read_text().splitlines():
        r = json.loads(line)
        name = Path(r["source"]).parent.name
        if r.get("T_tgt_src") is None:
            print(f"{name:32s} error: {r.get('error')}")
            continue
        folder = (args.summary.parent / r["source"]).parent
        ok, rot, share = right(np.array(r["T_tgt_src"]), folder)
        right_refused += ok and not r["passed"]
        info = json.loads((folder / "info.json").read_text())
        cm = 100 * share * info.get("size", info.get("scene_size_m"))
        fb = r.get("fallback") or {}
        t = r.get("timings_s", {})
        stages = " ".join(f"{k}={v:.2f}" for k, v in t.items() if v >= 0.05)
        print(
            f"{name:32s} {'right' if ok else 'WRONG'} rot {rot:6.2f} trans {100 * share:5.1f}% "
            f"({cm:.1f} cm) "
            f"conf {r['confidence']:.2f} {'pass' if r['passed'] else 'fail'} "
            f"learned {fb.get('learned_confidence', r['confidence']):.2f} "
            f"fb {'used' if fb.get('used') else ('ran' if fb else '-')}  {stages}"
        )
    counts = {**_count_byoc(args.summary), "right_but_refused": right_refused}
    print(" ".join(f"{k} {v}" for k, v in counts.items()))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="step", required=True)
    p = sub.add_parser("make")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--shapes", nargs="+", default=["blob", "superquadric", "torus", "blobs"])
    p.add_argument("--views", nargs="+", default=["turntable", "handheld"])
    p.add_argument("--angles", nargs="+", type=float, default=[30.0, 60.0])
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    p.add_argument("--sizes", nargs="+", type=float, default=list(SIZES), help="m, in turn")
    p.add_argument("--noise", type=float, default=1e-4, help="range noise, m (default 0.1 mm)")
    p.add_argument("--outliers", type=float, default=0.0, help="share of returns off the surface")
    p = sub.add_parser("make-tabletop")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--sizes", nargs="+", type=float, default=list(SIZES), help="m")
    p.add_argument("--angles", nargs="+", type=float, default=[20.0, 40.0, 60.0, 80.0])
    p.add_argument("--cache", type=Path, help="folder for the fused mesh (outside the repo)")
    p = sub.add_parser("scale")
    p.add_argument("src", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--factor", type=float, default=1000.0)
    p = sub.add_parser("o3d-loop")
    p.add_argument("pairs", type=Path)
    p.add_argument("--out-dir", type=Path, required=True)
    p = sub.add_parser("run")
    p.add_argument("dir", type=Path)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--baseline", help="another source tree (PYTHONPATH) run the same way")
    p.add_argument("--byoc-args", default="", help="extra options of register-batch")
    p = sub.add_parser("cues")
    p.add_argument("pairs", nargs="*", default=[], help="GROUP=DIR: pair folders of DIR")
    p.add_argument("--no-reference", action="store_true", help="only the folders given")
    p = sub.add_parser("judge")
    p.add_argument("summary", type=Path)
    args = parser.parse_args(argv)
    if args.step == "run" and not (args.dir / "pairs.txt").is_file():
        parser.error(f"{args.dir}: no pairs.txt (make it with 'make --out {args.dir}')")
    steps = {"make": make, "make-tabletop": make_tabletop, "o3d-loop": o3d_loop, "run": run}
    steps.update(cues=cues, judge=judge, scale=scale)
    steps[args.step](args)


if __name__ == "__main__":
    main()
