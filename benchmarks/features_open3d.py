"""`byoc features` descriptors in Open3D's correspondence RANSAC, as docs/pipelines.md shows,
over seeds.

Usage::

    python benchmarks/features_open3d.py [--weights W ...] [--seeds 10] [SOURCE TARGET T_GT]

Default pair: ``../shared/data/pairs/3dmatch_demo``. Per weights file (default: the shipped
ones): mutual nearest neighbours of the features, then Open3D's
``registration_ransac_based_on_correspondence`` (2 voxels, edge-length and distance
checkers, 100k iterations, 0.999) once per Open3D seed, and the same followed by Open3D's
point-to-plane ICP on the full clouds (2.5 cm); prints the rotation (deg) and translation
(cm) errors against the ground truth per seed and their ranges.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT.parent / "shared" / "data" / "pairs" / "3dmatch_demo"


def _errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    cos = (np.trace(T[:3, :3] @ T_gt[:3, :3].T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), 100 * float(
        np.linalg.norm(T[:3, 3] - T_gt[:3, 3])
    )


def main() -> int:
    import open3d as o3d

    from byoc_cli.io import read_point_cloud, read_transform
    from byoc_cli.pipeline.default_weights import default_weights_path
    from byoc_cli.pipeline.features import ByocExtractor
    from byoc_cli.pipeline.weights import load_weights

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pair", nargs="*", type=Path)
    parser.add_argument("--weights", type=Path, action="append")
    parser.add_argument("--seeds", type=int, default=10)
    args = parser.parse_args()
    src_path, tgt_path, gt_path = args.pair or [
        DEMO / "source.ply",
        DEMO / "target.ply",
        DEMO / "T_gt.txt",
    ]
    T_gt = read_transform(gt_path)
    clouds = [
        np.asarray(read_point_cloud(p).points, dtype=np.float64) for p in (src_path, tgt_path)
    ]
    reg = o3d.pipelines.registration

    def pcd(p):
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))

    full_src, full_tgt = pcd(clouds[0]), pcd(clouds[1])
    full_tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.05, max_nn=30))
    for weights in args.weights or [default_weights_path()]:
        loaded = load_weights(weights)
        voxel = float(loaded.metadata["voxel_size"])
        extractor = ByocExtractor(loaded.encoder, voxel)
        (pa, fa), (pb, fb) = [
            (f.points.double().numpy(), f.feats.numpy())
            for f in (extractor(torch.as_tensor(c, dtype=torch.float32)) for c in clouds)
        ]
        nn_ab, nn_ba = (fa @ fb.T).argmax(1), (fb @ fa.T).argmax(1)
        i = np.flatnonzero(nn_ba[nn_ab] == np.arange(len(nn_ab)))
        pairs = o3d.utility.Vector2iVector(np.c_[i, nn_ab[i]].astype(np.int32))
        coarse, refined = [], []
        for seed in range(args.seeds):
            o3d.utility.random.seed(seed)
            result = reg.registration_ransac_based_on_correspondence(
                pcd(pa),
                pcd(pb),
                pairs,
                2 * voxel,
                reg.TransformationEstimationPointToPoint(False),
                3,
                [
                    reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                    reg.CorrespondenceCheckerBasedOnDistance(2 * voxel),
                ],
                reg.RANSACConvergenceCriteria(100000, 0.999),
            )
            coarse.append(_errors(np.asarray(result.transformation), T_gt))
            icp = reg.registration_icp(
                full_src,
                full_tgt,
                voxel,
                result.transformation,
                reg.TransformationEstimationPointToPlane(),
            )
            refined.append(_errors(np.asarray(icp.transformation), T_gt))
        print(f"{Path(weights).name}: {len(i)} mutual matches")
        for label, rows in (("RANSAC", coarse), ("RANSAC + ICP", refined)):
            r, t = np.array(rows).T
            cells = " ".join(f"{a:.1f}/{b:.1f}" for a, b in rows)
            print(
                f"  {label:<13} deg/cm per seed: {cells}\n"
                f"  {'':<13} rotation {r.min():.1f}-{r.max():.1f} deg, "
                f"translation {t.min():.1f}-{t.max():.1f} cm"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
