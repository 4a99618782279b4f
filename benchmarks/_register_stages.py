"""`benchmarks/register.py` without `--only`: the registration's stages in process (`compact`
and `minkunet34c`, random weights) against Open3D FPFH + RANSAC at 5 and 2.5 cm, the sparse
convolution's FLOP/s and the peak RSS of a whole `byoc register` command.
"""

from __future__ import annotations

import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from _register_common import VOXEL
from byoc_cli.geometry import voxelize
from byoc_cli.io import read_point_cloud
from byoc_cli.pipeline.features import ByocExtractor
from byoc_cli.pipeline.register import RegisterConfig, estimate_transform, register_clouds
from byoc_cli.pipeline.weights import init_weights, save_weights


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


def print_in_process(src_path: Path, tgt_path: Path, repeats: int) -> None:
    """Print the in-process stages of both encoders on the pair, Open3D's times and the
    ratios, the sparse convolution's FLOP/s and the peak RSS of the whole command."""
    src_np = read_point_cloud(src_path).points
    tgt_np = read_point_cloud(tgt_path).points
    src, tgt = torch.from_numpy(src_np), torch.from_numpy(tgt_np)
    print(
        f"pair: {src_path.name} ({len(src_np)} pts) -> {tgt_path.name} ({len(tgt_np)} pts); "
        f"torch threads {torch.get_num_threads()}; voxel {VOXEL} m; repeats {repeats}"
    )

    rows = [bench_byoc(arch, src, tgt, repeats) for arch in ("compact", "minkunet34c")]
    o3d_5 = bench_open3d(src_np, tgt_np, 0.05, max(1, repeats // 2))
    o3d_25 = bench_open3d(src_np, tgt_np, 0.025, max(1, repeats // 2))

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
        flops = conv_vs_matmul(voxels, channels=64, repeats=max(5, 3 * repeats))
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
