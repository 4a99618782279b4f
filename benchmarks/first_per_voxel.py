"""The first point per voxel (`geometry/sampling.py:first_of_keys`) against numpy's unique.

The auto voxel's scan-line measure keeps the first point of each voxel of a whole cloud (the
points `voxelize` keeps) before it looks at their neighbourhoods: the increasing indices of
the first occurrence of each voxel key. `np.unique(keys, return_index=True)` sorts the keys
with a stable sort, which numpy runs as a merge sort on int64; `first_of_keys` uses torch's
stable sort (a radix sort on the CPU) and marks the first index of each run. Both give the
same indices; the script checks that and prints the median seconds of --repeat runs and the
ratio, on the demo pair's source (a Kinect fragment) and LiDAR-like grounds of 100k and 1M
points (`benchmarks/kdtree.py`), at twice each cloud's point spacing (the measure's voxel).

Usage: python benchmarks/first_per_voxel.py [--repeat 5] [--sizes 100000 1000000]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from byoc_cli.geometry.sampling import first_of_keys, nearest_spacing
from kdtree import DATA, lidar_ground, median_seconds


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """``(N,)`` int64 keys of the voxels of ``points (N, 3)`` (as `_first_per_voxel`)."""
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    return (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]


def with_numpy(keys: np.ndarray) -> np.ndarray:
    return np.sort(np.unique(keys, return_index=True)[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    args = parser.parse_args()
    torch.set_num_threads(1)
    from byoc_cli.api import load_cloud

    clouds = {"demo source": load_cloud(DATA / "pairs" / "3dmatch_demo" / "source.ply")}
    clouds.update({f"ground {n // 1000}k": lidar_ground(n) for n in args.sizes})
    print(f"{'cloud':14s} {'points':>9s} {'kept':>9s} {'numpy':>9s} {'byoc':>9s} {'ratio':>6s}")
    for name, points in clouds.items():
        points = np.ascontiguousarray(points, dtype=np.float64)
        keys = voxel_keys(points, 2.0 * nearest_spacing(torch.from_numpy(points)))
        kept = first_of_keys(keys)
        if not np.array_equal(kept, with_numpy(keys)):
            raise SystemExit(f"{name}: first_of_keys differs from numpy's unique")
        slow = median_seconds(with_numpy, keys, args.repeat)
        fast = median_seconds(first_of_keys, keys, args.repeat)
        print(
            f"{name:14s} {len(points):9d} {len(kept):9d} {slow:8.4f}s {fast:8.4f}s "
            f"{slow / fast:6.2f}"
        )


if __name__ == "__main__":
    main()
