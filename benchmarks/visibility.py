"""The visibility check's measure on register-batch results and on the ground truth: how much of
each cloud lies in the other's free space (pipeline/visibility.py), for right and wrong results.

Usage::

    python benchmarks/visibility.py --make-frames OUT
    python benchmarks/visibility.py [--fragments DEV SUMMARY] [--folders NAME SUMMARY ...]
        [--cut SUMMARY] [--face-bins 90] [--grow 2] [--any-bin] [--thresholds 0.06 0.09 0.12]

* ``--make-frames OUT``: the posed depth-frame pairs of ../shared/data at the gaps of
  :data:`FRAME_GAPS` (297 pairs), one folder each (``source.npy``, ``target.npy``, ``T_gt.txt``)
  with ``OUT/pairs.txt`` for ``register-batch``; then ``--folders NAME OUT/SUMMARY``.

* ``--fragments DEV SUMMARY``: a 3DMatch-layout benchmark (``byoc make-fragments``; the truth
  from its ``gt.log``) and a ``register-batch`` summary of its pairs
  (``benchmarks/low_overlap_default.py`` writes one); right: the official RMSE at most 0.2 m
  (or, without ``gt.info``, the source's points' RMSE) and within 5 deg.
* ``--folders NAME SUMMARY``: pairs in folders with ``T_gt.txt`` (Kinect frames); right within
  5 deg and 10 cm. ``tum_fr1_rpy`` pairs are listed apart (its ground truth is off by several
  degrees where the camera turns fast).
* ``--cut SUMMARY``: the results of ``cut_pairs.py`` pairs measured on the whole fragments they
  were cut from (the cuts take away surfaces the sensor saw, which a visibility check reads as
  free space); right by ``cut_pairs.py``'s criterion.

The measure runs on each cloud's first point per 2.5 cm voxel, as ``register`` does at the
features' own voxel. Printed per set: the results that pass the gate, right and wrong, the
largest share of a right one and of the ground truth, and per threshold the wrong results
above it and the right ones lost. ``--face-bins``, ``--grow`` and ``--any-bin`` measure other
settings of the range image (``geometry/visibility.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

VOXEL = 0.025
#: the depth-frame pairs of ``--make-frames``: sequence and frame gaps
FRAME_GAPS = (
    ("tum_fr1_desk_full", (10, 20, 30, 40, 50, 60)),
    ("tum_fr3_cabinet", (1, 2, 4, 6, 8)),
    ("realsense_tabletop", (5, 10, 15, 25, 30, 35)),
    ("tum_fr1_rpy", (20, 30, 50, 60)),
    ("tum_fr1_desk", (2, 4, 8)),
)
DATA = Path(
    os.environ.get("BYOC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
FRAGMENTS = DATA / "3dmatch"
SAMPLE = FRAGMENTS / "sample" / "3DMatch"


def rotation_deg(T: np.ndarray, G: np.ndarray) -> float:
    import torch

    from byoc_cli.geometry import rotation_error_deg

    return float(rotation_error_deg(torch.from_numpy(T), torch.from_numpy(G)))


def rmse(points: np.ndarray, T: np.ndarray, G: np.ndarray) -> float:
    d = points @ (T[:3, :3] - G[:3, :3]).T + (T[:3, 3] - G[:3, 3])
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


class Clouds:
    """Each file's first point per voxel, read once."""

    def __init__(self) -> None:
        self.kept: dict[str, np.ndarray] = {}

    def __call__(self, path: Path) -> np.ndarray:
        import torch

        from byoc_cli.api import load_cloud
        from byoc_cli.geometry import voxelize

        key = str(Path(path).resolve())
        if key not in self.kept:
            points = np.asarray(load_cloud(key, scale=1.0), dtype=np.float64)
            kept = voxelize(torch.from_numpy(points), VOXEL).point_index.numpy()
            self.kept[key] = points[kept]
        return self.kept[key]


def _records(summary: Path) -> list[dict]:
    rows = [json.loads(line) for line in summary.read_text().splitlines() if line.strip()]
    return [r for r in rows if r.get("T_tgt_src") is not None]


def fragments(root: Path, summary: Path, clouds: Clouds, image: dict) -> list[tuple]:
    from byoc_cli.evaluation.benchmark import load_benchmark_pairs
    from byoc_cli.evaluation.metrics import registration_rmse
    from byoc_cli.io.threedmatch import discover_benchmark

    pairs = load_benchmark_pairs(discover_benchmark(root)).pairs
    truth = {(str(p.source.resolve()), str(p.target.resolve())): p for p in pairs}
    rows = []
    for r in _records(summary):
        pair = truth[(str(Path(r["source"]).resolve()), str(Path(r["target"]).resolve()))]
        src, tgt = clouds(pair.source), clouds(pair.target)
        T = np.array(r["T_tgt_src"])
        if pair.info is not None:
            error = registration_rmse(T, pair.T_gt, pair.info)
        else:
            error = rmse(src, T, pair.T_gt)
        right = error <= 0.2 and rotation_deg(T, pair.T_gt) < 5
        rows.append(
            (
                "fragments",
                right,
                r["passed"],
                _share(src, tgt, T, image),
                _gt(src, tgt, pair.T_gt, image),
            )
        )
    return rows


def folders(name: str, summary: Path, clouds: Clouds, image: dict) -> list[tuple]:
    rows = []
    for r in _records(summary):
        source = summary.parent / r["source"]
        G = np.loadtxt(source.parent / "T_gt.txt")
        T = np.array(r["T_tgt_src"])
        src, tgt = clouds(source), clouds(summary.parent / r["target"])
        right = rotation_deg(T, G) < 5 and np.linalg.norm(T[:3, 3] - G[:3, 3]) < 0.1
        label = name + (" (tum_fr1_rpy)" if "rpy" in r["source"] else "")
        rows.append(
            (label, right, r["passed"], _share(src, tgt, T, image), _gt(src, tgt, G, image))
        )
    return rows


def cut(summary: Path, clouds: Clouds, image: dict) -> list[tuple]:
    rows = []
    for r in _records(summary):
        folder = (summary.parent / r["source"]).parent
        info = json.loads((folder / "info.json").read_text())
        scene = SAMPLE / info["scene"]
        src = clouds(scene / f"cloud_bin_{info['source_fragment']}.ply")
        tgt = clouds(scene / f"cloud_bin_{info['target_fragment']}.ply")
        G, T = np.loadtxt(folder / "T_gt.txt"), np.array(r["T_tgt_src"])
        right = rmse(src, T, G) <= 0.2 and rotation_deg(T, G) < 5
        rows.append(("cut (whole fragments)", right, r["passed"], _share(src, tgt, T, image), None))
    return rows


def _share(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, image: dict) -> float:
    from byoc_cli.pipeline.visibility import free_space

    return free_space(src, tgt, T, VOXEL, **image)["free_space"]


def _gt(src, tgt, G, image) -> float:
    return _share(src, tgt, G, image)


def table(rows: list[tuple], thresholds: list[float]) -> list[str]:
    lines = []
    for name in dict.fromkeys(r[0] for r in rows):
        mine = [r for r in rows if r[0] == name]
        right = [r[3] for r in mine if r[1] and r[2]]
        wrong = [r[3] for r in mine if not r[1] and r[2]]
        truth = [r[4] for r in mine if r[4] is not None]
        head = f"{name}: {len(mine)} results, passing {len(right)} right / {len(wrong)} wrong"
        head += f"; largest share: right {max(right, default=0):.3f}"
        if truth:
            head += f", ground truth {max(truth):.3f}"
        lines.append(head)
        for th in thresholds:
            caught = sum(x > th for x in wrong)
            lost = sum(x > th for x in right)
            lines.append(f"  above {th:g}: wrong {caught} of {len(wrong)}, right lost {lost}")
    return lines


def make_frames(out: Path) -> int:
    """Write the pairs of :data:`FRAME_GAPS` under ``out``; how many."""
    from byoc_cli.evaluation.pairs import rgbd_pairs

    rgbd = DATA / "rgbd"
    lines = []
    for sequence, gaps in FRAME_GAPS:
        for gap in gaps:
            pairs, _ = rgbd_pairs([rgbd / sequence], spacing=gap)
            for pair in pairs:
                name = pair.name.replace(":", "_").replace("/", "_") + f"_s{gap}"
                folder = out / name
                folder.mkdir(parents=True, exist_ok=True)
                for ref, file in ((pair.source, "source.npy"), (pair.target, "target.npy")):
                    np.save(folder / file, np.asarray(ref.load(), dtype=np.float32))
                np.savetxt(folder / "T_gt.txt", pair.T_gt)
                lines.append(f"{name}/source.npy {name}/target.npy out/{name}.txt")
    (out / "out").mkdir(parents=True, exist_ok=True)
    (out / "pairs.txt").write_text("\n".join(lines) + "\n")
    return len(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--make-frames", type=Path, metavar="OUT")
    parser.add_argument("--fragments", nargs=2, metavar=("DEV", "SUMMARY"), type=Path)
    parser.add_argument(
        "--folders", nargs=2, action="append", default=[], metavar=("NAME", "SUMMARY")
    )
    parser.add_argument("--cut", type=Path, metavar="SUMMARY")
    parser.add_argument("--face-bins", type=int, default=None)
    parser.add_argument("--grow", type=int, default=None)
    parser.add_argument(
        "--any-bin", action="store_true", help="empty bins take their neighbours' range"
    )
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.06, 0.09, 0.12])
    args = parser.parse_args()
    if args.make_frames:
        print(f"{make_frames(args.make_frames)} pairs")
        return
    image: dict = {}
    if args.face_bins is not None:
        image["bins"] = args.face_bins
    if args.grow is not None:
        image["grow"] = args.grow
    if args.any_bin:
        image["measured_only"] = False
    clouds, rows = Clouds(), []
    if args.fragments:
        rows += fragments(*args.fragments, clouds, image)
    for name, summary in args.folders:
        rows += folders(name, Path(summary), clouds, image)
    if args.cut:
        rows += cut(args.cut, clouds, image)
    if not rows:
        sys.exit("nothing to measure: give --fragments, --folders or --cut")
    print("\n".join(table(rows, args.thresholds)))


if __name__ == "__main__":
    main()
