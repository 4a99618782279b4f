"""Which estimator settings register learned features best: a sweep on development pairs.

Usage::

    python benchmarks/estimators.py --weights W.safetensors \
        [--fragments ROOT ...] [--rgbd-dir SEQ --spacing 10 ...] [--limit 40] [--seeds 1]

Features are computed once per cloud (the weights' voxel), then every setting below runs on
the same features: randomized Procrustes (the paper's) and RANSAC, with 200 / 500 / 1000
ratio-test correspondences per direction, 5000 / 10000 points, with and without mutual
filtering, each without and with point-to-plane ICP at the end (on the kept points, on the
full-resolution points, coarse-to-fine on the full-resolution points as ``register-scans``
does, or ``refine``: ``byoc register --refine multiscale``, the learned default). ``--icp``,
``--max-points`` and ``--num-correspondences`` replace the grid's values (RANSAC only when
given); ``--from-gt`` starts the refinement at the ground truth (how far it moves a correct
pose). Printed per pair set:
success (rotation < 15 deg and translation < 30 cm), rotation accuracy at 5 deg, translation
accuracy at 10 cm, median errors and the median seconds of matching + fitting (+ ICP).
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch


def _pair_sets(args):
    from byoc_cli.evaluation.benchmark import load_benchmark_pairs
    from byoc_cli.evaluation.pairs import rgbd_pairs
    from byoc_cli.io.pointcloud import read_point_cloud
    from byoc_cli.io.threedmatch import discover_benchmark

    sets = {}
    for root in args.fragments or []:
        pairs = load_benchmark_pairs(discover_benchmark(root), limit=args.limit).pairs
        sets[f"fragments:{Path(root).name}"] = [
            (
                f"{p.scene}:{p.i}-{p.j}",
                str(p.source),
                str(p.target),
                p.T_gt,
                (lambda path=p.source: read_point_cloud(path).points),
                (lambda path=p.target: read_point_cloud(path).points),
            )
            for p in pairs
        ]
    for root in args.rgbd_dir or []:
        specs, _ = rgbd_pairs([root], spacing=args.spacing, limit=args.limit)
        sets[f"rgbd:{Path(root).name}@{args.spacing}"] = [
            (s.name, s.source.key, s.target.key, s.T_gt, s.source.load, s.target.load)
            for s in specs
        ]
    return sets


def _errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    delta = np.linalg.inv(T_gt) @ T
    cos = np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(delta[:3, 3]))


#: Open3D's coarse-to-fine ICP that register-scans and odometry ran before the one
#: refinement stack: (voxel, correspondence distance) in multiples of the fine voxel
OPEN3D_SCALES = ((4.0, 6.0), (2.0, 3.0), (1.0, 1.5))


def _open3d_levels(points: np.ndarray, fine: float) -> list:
    """Open3D clouds with normals at each of :data:`OPEN3D_SCALES`."""
    import open3d as o3d

    base = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    levels = []
    for factor, _ in OPEN3D_SCALES:
        cloud = base.voxel_down_sample(factor * fine)
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * factor * fine, max_nn=30)
        )
        levels.append(cloud)
    return levels


def _open3d_multiscale(src: list, tgt: list, T: np.ndarray, fine: float) -> np.ndarray:
    """Open3D point-to-plane ICP at each of :data:`OPEN3D_SCALES` (30 iterations each)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    for level, (_, distance) in enumerate(OPEN3D_SCALES):
        T = reg.registration_icp(
            src[level],
            tgt[level],
            distance * fine,
            T,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=30),
        ).transformation
    return np.asarray(T).copy()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", type=Path, required=True)
    parser.add_argument("--fragments", type=Path, action="append")
    parser.add_argument("--rgbd-dir", type=Path, action="append")
    parser.add_argument("--spacing", type=int, default=10)
    parser.add_argument("--limit", type=int, default=None)
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help="fewer settings")
    parser.add_argument(
        "--icp",
        action="append",
        help="none, kept-F, full-F, multiscale-F, refine (byoc's --refine multiscale) or "
        "refine-plain (the same without holding sliding directions)",
    )
    parser.add_argument(
        "--from-gt",
        action="store_true",
        help="start the refinement at the ground truth instead of the feature estimate "
        "(how far refinement alone moves a correct pose)",
    )
    parser.add_argument("--max-points", type=int, action="append")
    parser.add_argument("--num-correspondences", type=int, action="append")
    args = parser.parse_args()

    from byoc_cli.evaluation.methods import open3d_icp
    from byoc_cli.pipeline.features import ByocExtractor
    from byoc_cli.pipeline.refine import refine_multiscale
    from byoc_cli.pipeline.register import RegisterConfig, estimate_transform
    from byoc_cli.pipeline.weights import load_weights

    loaded = load_weights(args.weights)
    voxel = float(loaded.metadata["voxel_size"])
    extractor = ByocExtractor(loaded.encoder, voxel)
    grid = {
        "estimator": ["ransac"] if args.quick else ["procrustes", "ransac"],
        "num_correspondences": [200, 1000] if args.quick else [200, 500, 1000],
        "max_points": [5000] if args.quick else [5000, 10000],
        "mutual": [False],
        # ICP: none; on the kept points at 2 voxels (5 cm); on the full-resolution points at
        # 0.4 voxel (1 cm); multiscale-0.4: coarse to fine on the full-resolution points at
        # 4, 2 and 1 times 0.4 voxel (Open3D's ICP, _open3d_multiscale below)
        "icp": ["none", "kept-2.0", "full-0.4"],
    }
    for key, given in (
        ("icp", args.icp),
        ("max_points", args.max_points),
        ("num_correspondences", args.num_correspondences),
    ):
        if given:
            grid[key] = given
            grid["estimator"] = ["ransac"]
    prepared: dict[tuple[str, float], object] = {}

    def multiscale(key: str, points: torch.Tensor, fine: float):
        if (key, fine) not in prepared:
            prepared[(key, fine)] = _open3d_levels(points.double().numpy(), fine)
        return prepared[(key, fine)]

    settings = [dict(zip(grid, v, strict=True)) for v in itertools.product(*grid.values())]
    for name, pairs in _pair_sets(args).items():
        feats: dict[str, object] = {}
        results = {i: [] for i in range(len(settings))}
        for label, key_s, key_t, T_gt, load_s, load_t in pairs:
            for key, load in ((key_s, load_s), (key_t, load_t)):
                if key not in feats:
                    points = torch.as_tensor(np.asarray(load()), dtype=torch.float32)
                    feats[key] = (points, extractor(points, label=key))
            (ps, fs), (pt, ft) = feats[key_s], feats[key_t]
            for n, s in enumerate(settings):
                for seed in range(args.seeds):
                    config = RegisterConfig(
                        estimator=s["estimator"],
                        num_correspondences=s["num_correspondences"],
                        max_points=s["max_points"],
                        seed=seed,
                    )
                    t0 = time.perf_counter()
                    try:
                        T = estimate_transform(fs, ft, config, voxel).T_tgt_src
                        if args.from_gt:
                            T = torch.as_tensor(np.asarray(T_gt), dtype=torch.float64)
                        if s["icp"].startswith("multiscale"):
                            fine = float(s["icp"].split("-")[1]) * voxel
                            T = _open3d_multiscale(
                                multiscale(key_s, ps, fine),
                                multiscale(key_t, pt, fine),
                                T.double().numpy(),
                                fine,
                            )
                            T = torch.from_numpy(T)
                        elif s["icp"].startswith("refine"):
                            held = {"sliding": 0.0} if s["icp"] == "refine-plain" else {}
                            T = refine_multiscale(ps, pt, T, voxel, **held).T_tgt_src
                        elif s["icp"] != "none":
                            which, factor = s["icp"].split("-")
                            a, b = (fs.points, ft.points) if which == "kept" else (ps, pt)
                            T = open3d_icp(a, b, T, float(factor) * voxel)
                        err = _errors(T.double().numpy(), T_gt)
                    except Exception:  # a failed fit counts as a failure
                        err = (180.0, 10.0)
                    results[n].append((*err, time.perf_counter() - t0))
            del label
        print(f"\n{name}: {len(pairs)} pairs x {args.seeds} seed(s)")
        print(
            f"{'setting':58s} {'succ%':>6s} {'r@5%':>6s} {'t@10%':>6s} "
            f"{'med r':>6s} {'med t':>6s} {'s':>6s}"
        )
        for n, s in enumerate(settings):
            r = np.asarray(results[n])
            label = (
                f"{s['estimator']:10s} corr {s['num_correspondences']:5d} "
                f"pts {s['max_points']:5d} icp {s['icp']}"
            )
            succ = np.mean((r[:, 0] < 15) & (r[:, 1] < 0.30)) * 100
            print(
                f"{label:58s} {succ:6.1f} {np.mean(r[:, 0] < 5) * 100:6.1f} "
                f"{np.mean(r[:, 1] < 0.10) * 100:6.1f} {np.median(r[:, 0]):6.2f} "
                f"{np.median(r[:, 1]) * 100:6.1f} {statistics.median(r[:, 2]):6.3f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
