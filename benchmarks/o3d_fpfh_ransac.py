"""Open3D's FPFH + RANSAC as one process, the peer of `byoc register` in benchmarks/register.py.

The Open3D tutorial pipeline (global registration): voxel down-sampling at 5 cm, normals
(radius 2 voxels, 30 neighbours), FPFH (radius 5 voxels, 100 neighbours), mutual-filter
RANSAC on feature matches (100k iterations, 0.999, distance 1.5 voxels). Reads the inputs
with byoc's reader (PLY, NPY, depth images), prints a JSON line of per-stage seconds.

Usage: python benchmarks/o3d_fpfh_ransac.py SOURCE TARGET [--intrinsics F --depth-scale D]
"""

from __future__ import annotations

import argparse
import json
import time

VOXEL = 0.05


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source")
    parser.add_argument("target")
    parser.add_argument("--intrinsics")
    parser.add_argument("--depth-scale", type=float, default=1000.0)
    args = parser.parse_args()
    start = time.perf_counter()
    import open3d as o3d

    from byoc_cli.api import load_cloud

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration
    imported = time.perf_counter()
    load = {"intrinsics": args.intrinsics, "depth_scale": args.depth_scale}
    clouds = [load_cloud(path, **load) for path in (args.source, args.target)]
    loaded = time.perf_counter()

    def prep(points):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        down = pcd.voxel_down_sample(VOXEL)
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * VOXEL, max_nn=30))
        fpfh = reg.compute_fpfh_feature(
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * VOXEL, max_nn=100)
        )
        return down, fpfh

    (src, f_src), (tgt, f_tgt) = (prep(points) for points in clouds)
    featured = time.perf_counter()
    dist = 1.5 * VOXEL
    o3d.utility.random.seed(0)
    reg.registration_ransac_based_on_feature_matching(
        src,
        tgt,
        f_src,
        f_tgt,
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
    done = time.perf_counter()
    stages = {
        "import": imported - start,
        "load": loaded - imported,
        "features": featured - loaded,
        "ransac": done - featured,
    }
    print(json.dumps(stages))


if __name__ == "__main__":
    main()
