"""Speed of the plain-PyTorch sparse convolution and of the geometric encoders on CPU.

Prints, for one real 3DMatch fragment voxelised at 2.5 cm:

* the useful GFLOP/s of a 64 -> 64 submanifold 3x3x3 convolution (useful FLOPs =
  active kernel pairs x 64 x 64 x 2, the centre offset included);
* the GFLOP/s of dense matmuls of the same FLOP count: ``(num_pairs, 64) @ (64, 64)`` (the
  comparison the speed bar uses) and ``(num_sites, 64) @ (64, 64)`` repeated
  ``num_pairs / num_sites`` times (cache-resident blocks, the harder reference), with
  the ratios;
* the kernel-map construction time;
* the per-cloud encode time (eval mode, ``torch.inference_mode()``, kernel maps included)
  of ``compact`` and ``minkunet34c``.

Timings are medians of interleaved repeats (the machine may be shared). Run:
``python benchmarks/sparse_conv.py [--ply FILE] [--threads N] [--repeats R]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData

from byoc_cli.geometry import voxelize
from byoc_cli.models.encoder import build_encoder, encode_voxels
from byoc_cli.models.sparse import CoordinateManager, sparse_conv

VOXEL_SIZE = 0.025
CHANNELS = 64
SHARED = Path(
    os.environ.get("BYOC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
DEFAULT_PLY = SHARED / "3dmatch" / "sample" / "3DMatch" / "7-scenes-redkitchen" / "cloud_bin_0.ply"


def load_voxels(path: Path) -> torch.Tensor:
    vertex = PlyData.read(str(path))["vertex"]
    points = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    return voxelize(torch.from_numpy(points), VOXEL_SIZE).coords


def interleaved_medians(functions: dict, repeats: int) -> dict[str, float]:
    """Median seconds of each function, run round-robin after one warm-up call each."""
    times: dict[str, list[float]] = {name: [] for name in functions}
    for fn in functions.values():
        fn()
    for _ in range(repeats):
        for name, fn in functions.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(t) for name, t in times.items()}


def conv_vs_matmul(voxels: torch.Tensor, channels: int = CHANNELS, repeats: int = 21) -> dict:
    """Useful FLOP/s of a ``channels -> channels`` submanifold 3x3x3 conv vs dense matmuls.

    Args:
        voxels: ``(N, 3)`` int64 voxel coordinates of one cloud.
        channels: input and output width.
        repeats: interleaved repeats; medians are reported.

    Returns:
        dict with the active pair count, median milliseconds, GFLOP/s and the ratios
        ``sparse / dense_pairs`` (the bar's comparison) and ``sparse / dense_sites``.
    """
    n = voxels.shape[0]
    coords = torch.cat([voxels.new_zeros(n, 1), voxels], dim=1)
    gen = torch.Generator().manual_seed(0)
    kmap = CoordinateManager(coords).submanifold_map(1, 3)
    pairs = kmap.num_pairs
    flops = 2 * pairs * channels * channels
    feats = torch.randn(n, channels, generator=gen)
    weight = torch.randn(27, channels, channels, generator=gen) / channels**0.5
    dense_pairs = torch.randn(pairs, channels, generator=gen)
    dense_sites = torch.randn(n, channels, generator=gen)
    matrix = torch.randn(channels, channels, generator=gen)
    out_pairs = torch.empty(pairs, channels)
    out_sites = torch.empty(n, channels)
    site_blocks = max(1, round(pairs / n))

    def dense_by_sites() -> None:
        for _ in range(site_blocks):
            torch.mm(dense_sites, matrix, out=out_sites)

    with torch.inference_mode():
        t = interleaved_medians(
            {
                "sparse": lambda: sparse_conv(feats, weight, kmap),
                "dense_pairs": lambda: torch.mm(dense_pairs, matrix, out=out_pairs),
                "dense_sites": dense_by_sites,
                "map": lambda: CoordinateManager(coords).submanifold_map(1, 3),
            },
            repeats,
        )
    sparse_rate = flops / t["sparse"] / 1e9
    pairs_rate = flops / t["dense_pairs"] / 1e9
    sites_rate = 2 * site_blocks * n * channels**2 / t["dense_sites"] / 1e9
    return {
        "sites": int(n),
        "active_pairs": int(pairs),
        "site_blocks": int(site_blocks),
        "sparse_ms": t["sparse"] * 1e3,
        "dense_pairs_ms": t["dense_pairs"] * 1e3,
        "dense_sites_ms": t["dense_sites"] * 1e3,
        "map_ms": t["map"] * 1e3,
        "sparse_gflops": sparse_rate,
        "dense_pairs_gflops": pairs_rate,
        "dense_sites_gflops": sites_rate,
        "ratio_pairs": sparse_rate / pairs_rate,
        "ratio_sites": sparse_rate / sites_rate,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ply", type=Path, default=DEFAULT_PLY)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--encoder-repeats", type=int, default=7)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    voxels = load_voxels(args.ply)
    n = voxels.shape[0]
    print(f"cloud: {args.ply.name}, {n} voxels at {VOXEL_SIZE} m")
    threads, load = torch.get_num_threads(), os.getloadavg()[0]
    print(f"torch {torch.__version__}, {threads} threads, load average {load:.2f}")
    if load > 0.5 * (os.cpu_count() or 1):
        print(
            "warning: busy machine, timings are unreliable (with OpenMP's default busy "
            "waiting every parallel region may cost a time slice: try OMP_WAIT_POLICY=PASSIVE)"
        )

    res = conv_vs_matmul(voxels, CHANNELS, args.repeats)
    pairs = res["active_pairs"]
    print(f"submanifold 3x3x3 map: {pairs} active pairs ({pairs / n:.2f} per site of 27)")
    print(
        f"sparse conv 64->64: {res['sparse_ms']:7.2f} ms  "
        f"{res['sparse_gflops']:6.1f} useful GFLOP/s"
    )
    print(
        f"dense ({pairs}, 64) @ (64, 64): {res['dense_pairs_ms']:7.2f} ms  "
        f"{res['dense_pairs_gflops']:6.1f} GFLOP/s  -> ratio {res['ratio_pairs']:.2f} (bar 0.40)"
    )
    print(
        f"dense {res['site_blocks']} x ({n}, 64) @ (64, 64): {res['dense_sites_ms']:7.2f} ms  "
        f"{res['dense_sites_gflops']:6.1f} GFLOP/s  -> ratio {res['ratio_sites']:.2f}"
    )
    print(f"kernel map build (3x3x3, stride 1): {res['map_ms']:.2f} ms")

    encoders = {}
    for arch in ("compact", "minkunet34c"):
        torch.manual_seed(0)
        encoders[arch] = build_encoder(arch).eval()
    with torch.inference_mode():
        t = interleaved_medians(
            {arch: (lambda e=e: encode_voxels(e, voxels)) for arch, e in encoders.items()},
            args.encoder_repeats,
        )
    for arch, seconds in t.items():
        params = sum(p.numel() for p in encoders[arch].parameters()) / 1e6
        print(f"encode {arch:12s} ({params:5.2f} M parameters): {seconds:.3f} s per cloud (median)")
    print(f"load {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
