"""`confidence.py check-truth`: every pair's ground truth refined a second time, with Open3D's
multiscale point-to-plane ICP instead of byoc's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from _confidence_records import load_records
from _confidence_set import part_of_set
from any_scan import errors

#: the levels of the second refinement (Open3D's point-to-plane ICP): voxel (metres times the
#: pair's scale) and iterations; correspondences within 1.5 voxels
CHECK_LEVELS = ((0.04, 40), (0.02, 40), (0.01, 40))


def open3d_truth(src: np.ndarray, tgt: np.ndarray, T_gt: np.ndarray, scale: float) -> np.ndarray:
    """``T_gt (4, 4)`` refined by Open3D's multiscale point-to-plane ICP on ``src (N, 3)`` and
    ``tgt (M, 3)``: a second refinement of the truth, by other code than byoc's."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    T = np.asarray(T_gt, dtype=np.float64)
    for voxel, iterations in CHECK_LEVELS:
        v = voxel * scale
        clouds = []
        for points in (src, tgt):
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            cloud = cloud.voxel_down_sample(v)
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(2.5 * v, 30))
            clouds.append(cloud)
        T = reg.registration_icp(
            *clouds,
            1.5 * v,
            T,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(1e-7, 1e-7, iterations),
        ).transformation
    return np.asarray(T)


def check_truth(paths: list[Path], out: Path, part: tuple[int, int]) -> None:
    """One line per pair of the collections with a ground truth (of ``part``, as
    :func:`part_of_set`): its second refinement."""
    records = {r["name"]: r for r in load_records(paths) if r.get("T_gt") is not None}
    with out.open("w") as file:
        for name, _, load_src, load_tgt, _, scale in part_of_set(part):
            if name not in records:
                continue
            T_gt = np.array(records[name]["T_gt"])
            T = open3d_truth(np.asarray(load_src()), np.asarray(load_tgt()), T_gt, scale)
            file.write(json.dumps({"name": name, "T_gt_open3d": T.tolist()}) + "\n")
            file.flush()
            rot, trans = errors(T, np.array(records[name].get("T_gt_refined", T_gt)))
            print(f"{name:40s} refinements apart: {rot:.2f} deg {100 * trans / scale:.2f} cm")
