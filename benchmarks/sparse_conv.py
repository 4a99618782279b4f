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
    coords = torch.cat([voxels.new_zeros(n, 1), voxels], dim=1)
    print(f"cloud: {args.ply.name}, {n} voxels at {VOXEL_SIZE} m")
    threads, load = torch.get_num_threads(), os.getloadavg()[0]
    print(f"torch {torch.__version__}, {threads} threads, load average {load:.2f}")
    if load > 0.5 * (os.cpu_count() or 1):
        print(
            "warning: busy machine, timings are unreliable (with OpenMP's default busy "
            "waiting every parallel region may cost a time slice: try OMP_WAIT_POLICY=PASSIVE)"
        )

    kmap = CoordinateManager(coords).submanifold_map(1, 3)
    pairs = kmap.num_pairs
    flops = 2 * pairs * CHANNELS * CHANNELS
    print(f"submanifold 3x3x3 map: {pairs} active pairs ({pairs / n:.2f} per site of 27)")

    feats = torch.randn(n, CHANNELS)
    weight = torch.randn(27, CHANNELS, CHANNELS) / CHANNELS**0.5
    dense_pairs = torch.randn(pairs, CHANNELS)
    dense_sites = torch.randn(n, CHANNELS)
    matrix = torch.randn(CHANNELS, CHANNELS)
    out_pairs = torch.empty(pairs, CHANNELS)
    out_sites = torch.empty(n, CHANNELS)
    site_blocks = round(pairs / n)

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
            args.repeats,
        )
    sparse_rate = flops / t["sparse"] / 1e9
    pairs_rate = flops / t["dense_pairs"] / 1e9
    sites_rate = 2 * site_blocks * n * CHANNELS**2 / t["dense_sites"] / 1e9
    ms = {name: seconds * 1e3 for name, seconds in t.items()}
    print(f"sparse conv 64->64: {ms['sparse']:7.2f} ms  {sparse_rate:6.1f} useful GFLOP/s")
    print(
        f"dense ({pairs}, 64) @ (64, 64): {ms['dense_pairs']:7.2f} ms  {pairs_rate:6.1f} GFLOP/s"
        f"  -> ratio {sparse_rate / pairs_rate:.2f} (bar 0.40)"
    )
    print(
        f"dense {site_blocks} x ({n}, 64) @ (64, 64): {ms['dense_sites']:7.2f} ms  "
        f"{sites_rate:6.1f} GFLOP/s  -> ratio {sparse_rate / sites_rate:.2f}"
    )
    print(f"kernel map build (3x3x3, stride 1): {ms['map']:.2f} ms")

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
