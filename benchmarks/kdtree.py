"""Which k-d tree answers the spacing query of `--voxel-size auto` fastest here.

The query (`geometry/sampling.py:nearest_spacing`): build a tree over a whole cloud, then the 8
nearest neighbours of 2,048 sampled points. Measured for pykdtree (what byoc uses), SciPy's
cKDTree and Open3D's KDTreeFlann (one Python call per query: its API), and for the voxel-grid
search byoc used before (`CellIndex` over the 27 cells around each query, the cell doubled
for queries that found no other point), which sized each query by the fullest cell.

Clouds: the demo pair's source (a Kinect fragment), a LiDAR-like ground (density falling with
the square of the range, as a spinning sensor's) of 100k and 1M points, and the same with
3,000 returns at the sensor (repeated points, as some sensors write for no return).

Prints the median seconds of --repeat runs per cloud and tree, and each one's ratio to
pykdtree's.

Usage: python benchmarks/kdtree.py [--repeat 5] [--sizes 100000 1000000] [--skip-grid]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
SAMPLES, K = 2048, 8


def lidar_ground(n: int, seed: int = 0, at_sensor: int = 0) -> np.ndarray:
    """``(n + at_sensor, 3)`` points on a plane 1.8 m below a sensor, range 3-80 m with a
    density that falls as 1 / range^2 (uniform in range), ``at_sensor`` copies of (0, 0, 0)."""
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(3, 80, n), rng.uniform(0, 2 * np.pi, n)
    pts = np.column_stack([r * np.cos(a), r * np.sin(a), np.full(n, -1.8)])
    return np.concatenate([pts, np.zeros((at_sensor, 3))])


def _queries(points: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(1)
    return points[rng.choice(len(points), min(SAMPLES, len(points)), replace=False)]


def pykdtree(points: np.ndarray) -> None:
    from pykdtree.kdtree import KDTree

    KDTree(points).query(_queries(points), k=K)


def scipy_ckdtree(points: np.ndarray) -> None:
    from scipy.spatial import cKDTree

    cKDTree(points).query(_queries(points), k=K)


def open3d_flann(points: np.ndarray) -> None:
    import open3d as o3d

    tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    for q in _queries(points):
        tree.search_knn_vector_3d(q, K)


def cell_grid(points: np.ndarray) -> None:
    """The voxel-grid search of byoc before the k-d tree (27 cells, doubled on a miss)."""
    import torch

    from byoc_cli.geometry.neighbors import CellIndex, nearest_candidates

    pts = torch.from_numpy(points)
    asked = torch.from_numpy(_queries(points))
    radius = float(np.median(np.linalg.norm(points - np.median(points, axis=0), axis=1)))
    if radius <= 0:  # most points in one place: the former measure gave up (spacing 0)
        return
    cell = 2.0 * radius / np.sqrt(len(points))
    for _ in range(24):
        index = CellIndex(pts, cell, max_per_cell=None)
        near = nearest_candidates(index, asked, k=16)
        d = torch.linalg.vector_norm(index.points[near.clamp_min(0)] - asked[:, None], dim=2)
        d = d.masked_fill((near < 0) | (d <= 0), float("inf")).min(dim=1).values
        asked = asked[~(d <= cell)]
        if len(asked) == 0:
            break
        cell *= 2


def median_seconds(fn, points: np.ndarray, repeat: int) -> float:
    """The median seconds of ``repeat`` calls ``fn(points)``."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn(points)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--skip-grid", action="store_true", help="leave out the cell grid")
    args = parser.parse_args()
    from byoc_cli.api import load_cloud

    clouds = {"demo source": load_cloud(DATA / "pairs" / "3dmatch_demo" / "source.ply")}
    for n in args.sizes:
        clouds[f"lidar {n}"] = lidar_ground(n)
        clouds[f"lidar {n} + 3000 at sensor"] = lidar_ground(n, at_sensor=3000)
    trees = {"pykdtree": pykdtree, "scipy cKDTree": scipy_ckdtree, "open3d": open3d_flann}
    if not args.skip_grid:
        trees["cell grid (before)"] = cell_grid
    print(f"{'cloud':32s} {'points':>8s} " + " ".join(f"{t:>20s}" for t in trees))
    for name, points in clouds.items():
        seconds = {t: median_seconds(fn, points, args.repeat) for t, fn in trees.items()}
        base = seconds["pykdtree"]
        cells = " ".join(f"{s:9.4f} s {s / base:6.1f}x" for s in seconds.values())
        print(f"{name:32s} {len(points):8d} {cells}", flush=True)


if __name__ == "__main__":
    main()
