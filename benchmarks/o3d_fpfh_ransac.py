"""Open3D's FPFH + RANSAC as one process, the peer of `byoc register` in benchmarks/register.py.

The Open3D tutorial pipeline (global registration): voxel down-sampling at 5 cm, normals
(radius 2 voxels, 30 neighbours), FPFH (radius 5 voxels, 100 neighbours), mutual-filter
RANSAC on feature matches (100k iterations, 0.999, distance 1.5 voxels). Reads the inputs
with byoc's reader (PLY, NPY, depth images), prints a JSON line of per-stage seconds; `--voxel`
sets another voxel (in the units of the points), `-o T.txt` writes the transform found.
`fpfh_ransac` is the pipeline for other scripts.

Usage: python benchmarks/o3d_fpfh_ransac.py SOURCE TARGET [--intrinsics F --depth-scale D]
           [--voxel 0.05] [-o T.txt]
"""

from __future__ import annotations

import argparse
import json
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy is imported in the timed import stage, as before
    import numpy as np

VOXEL = 0.05


def fpfh_ransac(src, tgt, voxel: float = VOXEL, seed: int = 0) -> tuple[np.ndarray, dict]:
    """Open3D's FPFH + RANSAC of ``src (N, 3)`` onto ``tgt (M, 3)`` at ``voxel`` (the tutorial
    pipeline above, every radius in voxels); returns ``(T (4, 4), seconds per stage)``,
    ``T`` mapping src into tgt's frame."""
    import numpy as np
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration
    start = time.perf_counter()

    def prep(points):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        down = pcd.voxel_down_sample(voxel)
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        fpfh = reg.compute_fpfh_feature(
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
        )
        return down, fpfh

    (src_down, f_src), (tgt_down, f_tgt) = (prep(points) for points in (src, tgt))
    featured = time.perf_counter()
    dist = 1.5 * voxel
    o3d.utility.random.seed(seed)
    result = reg.registration_ransac_based_on_feature_matching(
        src_down,
        tgt_down,
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
    stages = {"features": featured - start, "ransac": done - featured}
    return np.asarray(result.transformation), stages


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source")
    parser.add_argument("target")
    parser.add_argument("--intrinsics")
    parser.add_argument("--depth-scale", type=float, default=1000.0)
    parser.add_argument("--voxel", type=float, default=VOXEL, help="in the units of the points")
    parser.add_argument("-o", "--output", help="write T (4 lines of 4 numbers) here")
    args = parser.parse_args()
    start = time.perf_counter()
    import open3d  # noqa: F401  (timed as the import stage)

    from byoc_cli.api import load_cloud

    imported = time.perf_counter()
    load = {"intrinsics": args.intrinsics, "depth_scale": args.depth_scale}
    clouds = [load_cloud(path, **load) for path in (args.source, args.target)]
    loaded = time.perf_counter()
    T, stages = fpfh_ransac(*clouds, voxel=args.voxel)
    if args.output:
        import numpy as np

        np.savetxt(args.output, T, fmt="%.17g")
    stages = {"import": imported - start, "load": loaded - imported, **stages}
    print(json.dumps(stages))


if __name__ == "__main__":
    main()
