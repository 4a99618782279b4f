"""How many kept points should enter matching? The `--max-points` sweep behind the default.

For every ground-truth pair of the 3DMatch sample (3DMatch and 3DLoMatch records among the
redkitchen fragments) and the `pairs/3dmatch_demo` pair, the features of each fragment are
computed once; then, for each `--max-points` value and each seed, the pair is matched and fitted
with the command's defaults for that feature type (`fpfh`: 5 cm, RANSAC, 1000 matches per
direction; `byoc`: the weights' voxel, randomized Procrustes, 200 matches per direction), and
with FPFH at the byoc pipeline's settings (2.5 cm, about 20k kept points per fragment). It
prints, per feature type and value, the success rate (rotation error < 15 deg and translation
error < 30 cm, the 3DMatch success criterion), the median rotation / translation errors and the
median matching + fitting time.

Usage::

    python benchmarks/max_points.py [--weights RUN/weights.safetensors] [--seeds 3]
        [--values 1000 2500 5000 10000 0]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from byoc_cli.geometry import rotation_error_deg, translation_error
from byoc_cli.io import read_point_cloud, read_transform
from byoc_cli.io.threedmatch import read_gt_log
from byoc_cli.pipeline.features import ByocExtractor, FpfhExtractor
from byoc_cli.pipeline.register import RegisterConfig, estimate_transform
from byoc_cli.pipeline.weights import load_weights

SHARED = Path(
    os.environ.get("BYOC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
SAMPLE = SHARED / "3dmatch" / "sample"
SCENE = "7-scenes-redkitchen"


def sample_pairs() -> list[tuple[str, Path, Path, np.ndarray]]:
    """``(name, source path, target path, T_tgt_src)`` of the sample's and the demo's pairs."""
    pairs = []
    for bench in ("3DMatch", "3DLoMatch"):
        root = SAMPLE / bench
        for rec in read_gt_log(root / f"{SCENE}-evaluation" / "gt.log"):
            src = root / SCENE / f"cloud_bin_{rec.j}.ply"
            tgt = root / SCENE / f"cloud_bin_{rec.i}.ply"
            pairs.append((f"{bench} {rec.j}->{rec.i}", src, tgt, rec.T_tgt_src))
    demo = SHARED / "pairs" / "3dmatch_demo"
    pairs.append(
        ("demo", demo / "source.ply", demo / "target.ply", read_transform(demo / "T_gt.txt"))
    )
    return pairs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", type=Path, default=None, help="also sweep byoc features")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--values", type=int, nargs="+", default=[1000, 2500, 5000, 10000, 0])
    args = parser.parse_args()

    setups = {
        "fpfh": (FpfhExtractor(0.05), 0.05, dict(estimator="ransac", num_correspondences=1000)),
        # the byoc pipeline's density and estimator, with a descriptor that needs no training
        "fpfh --voxel-size 0.025 --estimator procrustes --num-correspondences 200": (
            FpfhExtractor(0.025),
            0.025,
            {},
        ),
    }
    if args.weights is not None:
        loaded = load_weights(args.weights)
        voxel = float(loaded.metadata["voxel_size"])
        setups["byoc"] = (ByocExtractor(loaded.encoder, voxel), voxel, {})
    pairs = sample_pairs()
    print(f"{len(pairs)} pairs, seeds 0..{args.seeds - 1}, torch threads {torch.get_num_threads()}")

    for name, (extractor, voxel, overrides) in setups.items():
        cache: dict[Path, object] = {}

        def features(path: Path, extractor=extractor, cache=cache):
            if path not in cache:
                cache[path] = extractor(torch.from_numpy(read_point_cloud(path).points))
            return cache[path]

        print(f"\n--features {name} (voxel {voxel} m, {overrides or 'defaults'})")
        print(
            f"{'max-points':>10} {'success':>8} {'rot med':>8} {'trans med':>10} {'match+fit':>10}"
        )
        for value in args.values:
            ok, rots, trans, times = [], [], [], []
            for _, src, tgt, T_gt in pairs:
                f_src, f_tgt = features(src), features(tgt)
                for seed in range(args.seeds):
                    config = RegisterConfig(max_points=value, seed=seed, **overrides)
                    start = time.perf_counter()
                    res = estimate_transform(f_src, f_tgt, config, voxel)
                    times.append(time.perf_counter() - start)
                    T = res.T_tgt_src
                    T_gt_t = torch.from_numpy(T_gt)
                    r = float(rotation_error_deg(T, T_gt_t))
                    t = float(translation_error(T, T_gt_t))
                    rots.append(r)
                    trans.append(t)
                    ok.append(r < 15.0 and t < 0.30)
            label = "all" if value == 0 else str(value)
            print(
                f"{label:>10} {100 * np.mean(ok):7.1f}% {statistics.median(rots):7.2f}d "
                f"{100 * statistics.median(trans):8.1f}cm {statistics.median(times):9.3f}s"
            )


if __name__ == "__main__":
    main()
