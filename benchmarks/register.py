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
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from byoc_cli.geometry import voxelize
from byoc_cli.io import read_point_cloud
from byoc_cli.pipeline.features import ByocExtractor
from byoc_cli.pipeline.register import RegisterConfig, estimate_transform, register_clouds
from byoc_cli.pipeline.weights import init_weights, save_weights

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
SAMPLE = DATA / "3dmatch" / "sample" / "3DMatch" / "7-scenes-redkitchen"
VOXEL = 0.025
BYOC = [sys.executable, "-m", "byoc_cli.cli.main", "-q"]


def median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def bench_byoc(arch: str, src: torch.Tensor, tgt: torch.Tensor, repeats: int) -> dict:
    encoder, _ = init_weights(arch, seed=0)
    extractor = ByocExtractor(encoder, VOXEL)
    config = RegisterConfig()
    extractor(src)  # warm-up (allocator, thread pool)
    t_src, f_src = median_time(lambda: extractor(src), repeats)
    t_tgt, f_tgt = median_time(lambda: extractor(tgt), repeats)
    t_est, res = median_time(lambda: estimate_transform(f_src, f_tgt, config, VOXEL), repeats)
    t_all, _ = median_time(lambda: register_clouds(src, tgt, extractor, config), repeats)
    return {
        "arch": arch,
        "voxels_src": f_src.points.shape[0],
        "voxels_tgt": f_tgt.points.shape[0],
        "features_src_s": t_src,
        "features_tgt_s": t_tgt,
        "match_s": res.timings["match"],
        "fit_s": res.timings["fit"],
        "match_fit_verify_s": t_est,
        "register_s": t_all,
        "params": sum(p.numel() for p in encoder.parameters()),
    }


def bench_open3d(src: np.ndarray, tgt: np.ndarray, voxel: float, repeats: int) -> dict:
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration

    def run():
        def prep(points):
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            down = pcd.voxel_down_sample(voxel)
            down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
            fpfh = reg.compute_fpfh_feature(
                down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
            )
            return down, fpfh

        s, fs = prep(src)
        t, ft = prep(tgt)
        dist = 1.5 * voxel
        return reg.registration_ransac_based_on_feature_matching(
            s,
            t,
            fs,
            ft,
            True,
            dist,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [
                reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                reg.CorrespondenceCheckerBasedOnDistance(dist),
            ],
            reg.RANSACConvergenceCriteria(100000, 0.999),
        )

    o3d.utility.random.seed(0)
    t, result = median_time(run, repeats)
    return {"voxel": voxel, "register_s": t, "T": np.asarray(result.transformation)}


def peak_rss_of_command(src: Path, tgt: Path, weights: Path) -> float:
    """Peak RSS (MB) of a `byoc register` subprocess, via the child's rusage."""
    # `register` refuses to write over a device such as /dev/null: a temporary T file
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "T.txt"
        code = (
            "import sys; from byoc_cli.cli.main import cli; "
            f"sys.argv=['byoc','register','{src}','{tgt}','--weights','{weights}','-o','{out}']; "
            "cli()"
        )
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        subprocess.run([sys.executable, "-c", code], check=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(before, after) / 1024.0


def _sample_pairs(folder: Path) -> list[tuple[Path, Path]]:
    import itertools

    clouds = sorted(folder.glob("cloud_bin_*.ply"))
    pairs = list(itertools.combinations(clouds, 2))
    if not pairs:
        raise SystemExit(f"no cloud_bin_*.ply pairs in {folder} (set BYOC_SHARED_DATA)")
    return pairs


def _env(source: Path | None) -> dict[str, str] | None:
    """The environment of a command of another source tree (None: this one's)."""
    if source is None:
        return None
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": f"{source}{os.pathsep}{path}" if path else str(source)}


def _timed_batch(
    listing: Path, out: Path, extra: list[str], source: Path | None = None
) -> tuple[float, float]:
    """Wall and CPU seconds of one `byoc register-batch` process (``source``: of that tree)."""
    start = time.perf_counter()
    proc = subprocess.Popen(
        [*BYOC, "register-batch", str(listing), "--out-dir", str(out), *extra], env=_env(source)
    )
    _, status, usage = os.wait4(proc.pid, 0)
    assert os.waitstatus_to_exitcode(status) in (0, 3), status
    return time.perf_counter() - start, usage.ru_utime + usage.ru_stime


def batch_vs_loop(
    folder: Path, repeats: int, loop: bool = True, baseline: Path | None = None
) -> dict:
    """Whole-process pairs per second: `register-batch` (default, --features fpfh and the
    ``baseline`` tree's default, interleaved, ``repeats`` each) and, once, one `byoc register`
    process per pair."""
    pairs = _sample_pairs(folder)
    variants = [("default", [], None), ("fpfh", ["--features", "fpfh"], None)]
    if baseline is not None:
        variants.append(("baseline", [], baseline))
    runs: dict[str, list[tuple[float, float]]] = {name: [] for name, _, _ in variants}
    same_as_baseline = None
    with tempfile.TemporaryDirectory() as tmp:
        listing = Path(tmp) / "pairs.txt"
        listing.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        for k in range(repeats):
            for name, extra, source in variants:
                out = Path(tmp) / f"{name}{k}"
                runs[name].append(_timed_batch(listing, out, extra, source))
        if baseline is not None:
            same_as_baseline = all(
                (Path(tmp) / "default0" / f"{a.stem}__{b.stem}.txt").read_bytes()
                == (Path(tmp) / "baseline0" / f"{a.stem}__{b.stem}.txt").read_bytes()
                for a, b in pairs
            )
        loop_s, same = None, None
        if loop:
            start = time.perf_counter()
            for k, (a, b) in enumerate(pairs):
                out = Path(tmp) / f"single_{k}.txt"
                subprocess.run([*BYOC, "register", str(a), str(b), "-o", str(out)], check=True)
            loop_s = time.perf_counter() - start
            same = all(
                (Path(tmp) / f"single_{k}.txt").read_bytes()
                == (Path(tmp) / "default0" / f"{a.stem}__{b.stem}.txt").read_bytes()
                for k, (a, b) in enumerate(pairs)
            )
    return {
        "pairs": len(pairs),
        "runs": runs,
        "loop_s": loop_s,
        "same": same,
        "same_as_baseline": same_as_baseline,
    }


def print_batch(
    folder: Path, repeats: int = 1, loop: bool = True, baseline: Path | None = None
) -> None:
    load_before = os.getloadavg()[0]
    b = batch_vs_loop(folder, repeats, loop, baseline)
    n = b["pairs"]
    print(
        f"\nwhole process, {n} pairs ({folder.name}), median of {repeats} "
        f"(load average {load_before:.2f} -> {os.getloadavg()[0]:.2f}):"
    )
    med = {}
    for name, rs in b["runs"].items():
        wall, cpu = statistics.median(r[0] for r in rs), statistics.median(r[1] for r in rs)
        med[name] = wall
        label = "`byoc register-batch`" + {
            "fpfh": " --features fpfh",
            "baseline": " (baseline)",
        }.get(name, "")
        print(f"  {label:<40} {wall:6.1f} s, CPU {cpu:6.1f} s, {n / wall:.2f} pairs/s")
    print(f"  default / fpfh wall: {med['default'] / med['fpfh']:.2f}; bar: >= 2 pairs/s")
    if b["same_as_baseline"] is not None:
        print(
            f"  default / baseline wall: {med['default'] / med['baseline']:.2f}; T files "
            f"byte-identical to the baseline's: {b['same_as_baseline']}"
        )
    if b["loop_s"] is not None:
        loop_rate = n / b["loop_s"]
        print(
            f"  loop of `byoc register`: {b['loop_s']:.1f} s, {loop_rate:.2f} pairs/s; "
            f"batch / loop {n / med['default'] / loop_rate:.2f}x; "
            f"transforms byte-identical: {b['same']}"
        )


def whole_process(src: Path, tgt: Path, repeats: int) -> None:
    """Median wall time of whole `byoc register` processes: default against --features fpfh."""
    byoc = [sys.executable, "-m", "byoc_cli.cli.main", "-q", "register", str(src), str(tgt)]
    times: dict[str, list[float]] = {"default": [], "fpfh": []}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):  # interleaved, so that load changes hit both alike
            for name, extra in (("default", []), ("fpfh", ["--features", "fpfh"])):
                start = time.perf_counter()
                subprocess.run([*byoc, *extra, "-o", str(Path(tmp) / "T.txt")], check=True)
                times[name].append(time.perf_counter() - start)
    d, f = statistics.median(times["default"]), statistics.median(times["fpfh"])
    print(
        f"\nwhole `byoc register` process, {src.name} -> {tgt.name}, median of {repeats}:\n"
        f"  default (shipped weights): {d:.2f} s\n  --features fpfh: {f:.2f} s\n"
        f"  ratio default / fpfh: {d / f:.2f} (bar: <= 1)"
    )


# ------------------------------------------------------------------ whole processes under load

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
    tree: :func:`_env`), ``fpfh`` or ``open3d``."""
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
    env = _env(baseline) if variant == "baseline" else None
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
    src_np = read_point_cloud(src_path).points
    tgt_np = read_point_cloud(tgt_path).points
    src, tgt = torch.from_numpy(src_np), torch.from_numpy(tgt_np)
    print(
        f"pair: {src_path.name} ({len(src_np)} pts) -> {tgt_path.name} ({len(tgt_np)} pts); "
        f"torch threads {torch.get_num_threads()}; voxel {VOXEL} m; repeats {args.repeats}"
    )

    rows = [bench_byoc(arch, src, tgt, args.repeats) for arch in ("compact", "minkunet34c")]
    o3d_5 = bench_open3d(src_np, tgt_np, 0.05, max(1, args.repeats // 2))
    o3d_25 = bench_open3d(src_np, tgt_np, 0.025, max(1, args.repeats // 2))

    print("\nbyoc register, in process (median seconds)")
    print(
        f"{'encoder':<12}{'params':>10}{'voxels':>14}{'feat src':>10}{'feat tgt':>10}"
        f"{'match':>8}{'fit':>8}{'register':>10}"
    )
    for r in rows:
        print(
            f"{r['arch']:<12}{r['params']:>10,}{r['voxels_src']:>7}/{r['voxels_tgt']:<6}"
            f"{r['features_src_s']:>10.3f}{r['features_tgt_s']:>10.3f}{r['match_s']:>8.3f}"
            f"{r['fit_s']:>8.3f}{r['register_s']:>10.3f}"
        )
    print("\nOpen3D FPFH + RANSAC (mutual filter, 100k iterations, 0.999), median seconds")
    for o in (o3d_5, o3d_25):
        print(f"  voxel {o['voxel']:.3f} m: {o['register_s']:.3f} s")
    compact = rows[0]["register_s"]
    print("\nratios (Open3D time / byoc compact time; > 1 means byoc is faster)")
    print(f"  vs FPFH+RANSAC at 2.5 cm: {o3d_25['register_s'] / compact:.2f}x")
    print(f"  vs FPFH+RANSAC at 5 cm:   {o3d_5['register_s'] / compact:.2f}x")
    print(f"  minkunet34c / compact register time: {rows[1]['register_s'] / compact:.2f}x")

    try:
        from sparse_conv import conv_vs_matmul  # benchmarks/sparse_conv.py

        voxels = voxelize(src, VOXEL).coords
        flops = conv_vs_matmul(voxels, channels=64, repeats=max(5, 3 * args.repeats))
        print(
            f"\nsparse conv 3x3x3, 64 -> 64 channels on {flops['sites']} sites: "
            f"{flops['sparse_gflops']:.1f} useful GFLOP/s; dense matmul of the same shape "
            f"{flops['dense_pairs_gflops']:.1f} GFLOP/s -> ratio {flops['ratio_pairs']:.2f} "
            f"(bar 0.40); vs cache-resident site blocks {flops['ratio_sites']:.2f}"
        )
    except ImportError as exc:
        print(f"\nsparse conv benchmark unavailable: {exc}")

    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "compact.safetensors"
        encoder, meta = init_weights("compact", seed=0)
        save_weights(weights, encoder, meta)
        rss = peak_rss_of_command(src_path, tgt_path, weights)
    print(f"\npeak RSS of `byoc register` (compact, defaults): {rss:.0f} MB")
    print_batch(SAMPLE)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
