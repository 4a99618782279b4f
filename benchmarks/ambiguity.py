"""Ambiguity cues against right and wrong results that pass the gate (issue 35): a measurement,
no default changed.

Usage::

    python benchmarks/ambiguity.py --out eval/ [--fragments DEV] [--cache-dir features/] \
        [--sets dev-low dev-high 3DLoMatch-sample 3DMatch-sample kinect synthetic cut] \
        [--cut-dirs CUT ...] [--limit N] [--no-fallback] [--table-only]

Each pair is registered as ``byoc register`` registers it by default (``byoc eval-fmr``'s
``byoc`` method: the shipped weights, 5000 points, RANSAC, the multiscale refinement and its
restarts, the calibrated confidence; below the gate the FPFH second opinion, refined the same
way, is kept when more confident), then the cues of ``_ambiguity_cues.py`` are computed on
the kept result's correspondences and clouds. The sets: ``dev-low`` / ``dev-high`` (the
development fragments of docs/low-overlap.md, 10-30 % and above 30 %, ``--fragments``), the
3DMatch sample's 3DLoMatch and 3DMatch pairs, ``kinect`` (tum_fr1_desk_full frames 25 apart),
``synthetic`` (``_ambiguity_synth.py``: a slid pair and a clean one, no features) and ``cut``
(the folders of ``cut_pairs.py make`` given to ``--cut-dirs``, scored by ``cut_pairs.py``'s
criterion: RMSE of the source's points at most 0.2 m and within 5 deg).

A result is right when its official RMSE (``gt.info``) is at most 0.2 m, or, for pairs
without one (adjacent fragments, Kinect frames, synthetic), within 5 deg and 10 cm. Printed:
per band the results that pass the gate (confidence >= 0.45), right and wrong; for each cue and
threshold the wrong results it catches and the right ones it loses; the passing wrong results
one by one (with ``truth_inliers``: the correspondences within the inlier threshold under the
ground truth, and ``result_inliers``: under the result); per band, of the wrong results, how
many the result explains more correspondences of than the truth (then no estimator that
maximises the consensus finds the truth); the seconds of the cues. Records go to
``--out/ambiguity-<set>.json`` and are reused (delete one to run its set again).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
import zlib
from pathlib import Path

import _ambiguity_cues as cues_mod

ROOT = Path(__file__).resolve().parents[1]
RGBD = ROOT.parent / "shared" / "data" / "rgbd"
SETS = ("dev-low", "dev-high", "3DLoMatch-sample", "3DMatch-sample", "kinect", "synthetic", "cut")
#: band -> its sets
BANDS = {
    "low (10-30 %)": ("dev-low", "3DLoMatch-sample"),
    "high (dev, > 30 %)": ("dev-high",),
    "controls": ("3DMatch-sample", "kinect"),
    "synthetic": ("synthetic",),
    "cut (12-32 %)": ("cut",),
}
GATE = 0.45
RMSE, DEG, METRES = 0.2, 5.0, 0.10
#: cue -> thresholds of the sweep (a cue fires at or above its threshold)
SWEEP = {
    "seq_ratio": (0.3, 0.5, 0.7, 0.9),
    "seq_wratio": (0.3, 0.5, 0.7, 0.9),
    "seq_far_ratio": (0.3, 0.5, 0.7, 0.9, 1.0, 1.2),
    "ref_ratio": (0.7, 0.8, 0.9, 1.0),
    "ref_overlap_ratio": (0.7, 0.8, 0.9, 1.0),
    "slide_voxels": (3.0, 10.0, 20.0, 40.0),
    "restart_gain": (-0.05, -0.02, 0.0),
}
#: rows that fire when either cue does: (cue, threshold), (cue, threshold)
EITHER = (
    (("ref_ratio", 0.8), ("restart_gain", -0.02)),
    (("ref_ratio", 0.9), ("restart_gain", -0.02)),
)


def _solve(feats, clouds, config, voxel: float, refine_voxel: float, seed: int, T_gt=None):
    """``estimate_transform``'s matching, fit, refinement and verdict (no scan lines), with
    its correspondences, kept points and prepared clouds for the cues."""
    import torch

    from byoc_cli.matching import ratio_test_correspondences
    from byoc_cli.pipeline.register import _subset, sample_subset

    config = dataclasses.replace(config, seed=seed)
    src, tgt = feats
    generator = torch.Generator().manual_seed(config.seed)
    ps, fs = _subset(src, sample_subset(len(src.points), config.max_points, generator))
    pt, ft = _subset(tgt, sample_subset(len(tgt.points), config.max_points, generator))
    corr = ratio_test_correspondences(fs, ft, k=config.num_correspondences, mutual=config.mutual)
    p = ps[corr.src_idx].to(torch.float64)
    q = pt[corr.tgt_idx].to(torch.float64)
    w = corr.weight.detach().to(torch.float64)
    kept = (src.points, tgt.points)
    return _judged((p, q, w), kept, clouds, config, voxel, refine_voxel, T_gt)


def _judged(correspondences, kept, clouds, config, voxel, refine_voxel, T_gt=None):
    import torch

    from byoc_cli.pipeline.refine_levels import RefineCloud
    from byoc_cli.pipeline.register import _Timer
    from byoc_cli.pipeline.solve import Solver

    class _Kept:
        def __init__(self, points):
            self.points = points

    full = tuple(RefineCloud(c, refine_voxel) for c in clouds)
    src, tgt = _Kept(kept[0].to(torch.float64)), _Kept(kept[1].to(torch.float64))
    solver = Solver(src, tgt, full, voxel, refine_voxel, config, None)
    generator = torch.Generator().manual_seed(config.seed)
    timer = _Timer()
    start = time.perf_counter()
    refinement, verdict = solver.solve(correspondences, correspondences, generator, timer)
    seconds = time.perf_counter() - start
    found = cues_mod.ambiguity_cues(
        correspondences,
        refinement.T_tgt_src,
        solver.threshold,
        (src.points, tgt.points),
        full,
        (voxel, refine_voxel),
        config.seed,
    )
    if T_gt is not None:  # how many correspondences the ground truth explains
        p, q, _ = correspondences
        gap = cues_mod._residual(torch.as_tensor(T_gt, dtype=torch.float64), p, q)
        found["truth_inliers"] = int((gap < solver.threshold).sum())
        mine = cues_mod._residual(refinement.T_tgt_src.to(torch.float64), p, q)
        found["result_inliers"] = int((mine < solver.threshold).sum())
    return refinement.T_tgt_src, verdict, found, seconds


def _record(name, T, T_gt, info, verdict, found, seconds, **extra) -> dict:
    import torch

    from byoc_cli.evaluation.metrics import pose_errors, registration_rmse

    T_gt = torch.as_tensor(T_gt, dtype=torch.float64)
    rot, trans = pose_errors(T, T_gt)
    rmse = registration_rmse(T, T_gt, info) if info is not None else None
    right = rmse <= RMSE if rmse is not None else (rot < DEG and trans < METRES)
    return {
        "name": name,
        "confidence": verdict.confidence,
        "passed": verdict.confidence >= GATE,
        "right": bool(right),
        "rotation_error_deg": rot,
        "translation_error_m": trans,
        "rmse_m": rmse,
        "seconds": seconds,
        "restart_gain": verdict.cues.get("restart_gain", -1.0),
        "restart_return": verdict.cues.get("restart_return", 1.0),
        **extra,
        **found,
    }


class _Runner:
    """The learned method and its FPFH second opinion, with the features of each cloud."""

    def __init__(self, cache_dir: Path | None, fallback: bool) -> None:
        from byoc_cli.evaluation.cache import FeatureCache
        from byoc_cli.evaluation.methods import build_methods
        from byoc_cli.pipeline.default_weights import default_weights_path
        from byoc_cli.pipeline.recipe import PRESETS

        byoc, fpfh = build_methods(
            ["byoc", "fpfh-ransac"], [default_weights_path()], max_points=5000
        )
        self.byoc, self.fpfh = byoc, fpfh
        # the second opinion: the fpfh preset refined the same way, its own confidence model
        self.fpfh_config = dataclasses.replace(
            fpfh.config,
            refine="multiscale",
            confidence_model="fpfh",
            max_points=PRESETS["fpfh"].matching.max_points,
        )
        self.fallback = fallback
        self.cache = FeatureCache(cache_dir)
        self.points: dict[str, object] = {}

    def _clouds(self, refs):
        """The full points of the pair's clouds (the previous pair's are reused)."""
        import numpy as np
        import torch

        points = {}
        for key, _, load in refs:
            known = self.points.get(key)
            points[key] = (
                known
                if known is not None
                else torch.from_numpy(np.asarray(load(), dtype=np.float64))
            )
        self.points = points
        return tuple(points[key] for key, _, _ in refs)

    def register(self, refs, seed: int, T_gt=None):
        """``(T, verdict, cues, seconds, features)`` of the kept result of one pair; ``refs``:
        ``(key, identity, load)`` of source and target."""
        clouds = self._clouds(refs)
        out = None
        for method, config in ((self.byoc, self.byoc.config), (self.fpfh, self.fpfh_config)):
            spec = method.features
            feats = tuple(
                self.cache.get(spec.identity, identity, lambda c=c, s=spec: s.extractor(c))
                for (_, identity, _), c in zip(refs, clouds, strict=True)
            )
            voxel = method.features.voxel_size
            T, verdict, found, seconds = _solve(feats, clouds, config, voxel, voxel, seed, T_gt)
            if out is not None:
                seconds += out[3]
            if out is None or verdict.confidence > out[1].confidence:
                out = (T, verdict, found, seconds, method.features.key)
            if not self.fallback or out[1].confidence >= GATE:
                break
        return out


def _pairs(name: str, fragments: Path | None, limit: int | None, cut_dirs=()):
    """``(name, refs, T_gt, info, seed, overlap)`` of one set's pairs."""
    from byoc_cli.evaluation.cache import file_identity
    from byoc_cli.evaluation.fmr_protocol import pair_seed
    from byoc_cli.io.pointcloud import read_point_cloud

    if name == "cut":
        import numpy as np

        for folder in cut_dirs:
            lines = (folder / "pairs.txt").read_text().split("\n")
            for line in [line for line in lines if line.strip()][:limit]:
                source, target = (folder / part for part in line.split()[:2])
                refs = [
                    (
                        str(path),
                        file_identity(path),
                        lambda path=path: read_point_cloud(path).points,
                    )
                    for path in (source, target)
                ]
                pair = f"{folder.name}:{source.parent.name}"
                T_gt = np.loadtxt(source.parent / "T_gt.txt")
                info = json.loads((source.parent / "info.json").read_text())
                yield pair, refs, T_gt, None, zlib.crc32(pair.encode()), info["overlap"]
        return

    if name == "kinect":
        from byoc_cli.evaluation.pairs import rgbd_pairs

        found, _ = rgbd_pairs([RGBD / "tum_fr1_desk_full"], spacing=25, limit=limit)
        for p in found:
            refs = [(r.key, r.identity, r.load) for r in (p.source, p.target)]
            yield p.name, refs, p.T_gt, None, zlib.crc32(p.name.encode()), None
        return
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import low_overlap_estimators

    for pair in low_overlap_estimators._pairs(name, fragments, limit):
        refs = [
            (str(path), file_identity(path), lambda path=path: read_point_cloud(path).points)
            for path in (pair.source, pair.target)
        ]
        info = pair.info if pair.j - pair.i > 1 else None
        seed = pair_seed(0, pair.scene, pair.i, pair.j)
        yield f"{pair.scene}:{pair.i}-{pair.j}", refs, pair.T_gt, info, seed, pair.overlap


def _synthetic() -> list[dict]:
    from _ambiguity_synth import VOXEL, synthetic_pairs
    from byoc_cli.pipeline.recipe import PRESETS
    from byoc_cli.pipeline.register import register_config

    config = dataclasses.replace(register_config(PRESETS["byoc"]), seed=0)
    records = []
    for pair in synthetic_pairs():
        kept = (pair.kept_source, pair.kept_target)
        clouds = (pair.source, pair.target)
        T, verdict, found, seconds = _judged(
            pair.correspondences, kept, clouds, config, VOXEL, VOXEL, pair.T_gt
        )
        records.append(
            _record(pair.name, T, pair.T_gt, None, verdict, found, seconds, features="none")
        )
    return records


def _run(name, args, runner_box) -> list[dict]:
    if name == "synthetic":
        return _synthetic()
    if runner_box[0] is None:
        runner_box[0] = _Runner(args.cache_dir, not args.no_fallback)
    runner = runner_box[0]
    records = []
    start = time.perf_counter()
    for n, (pair, refs, T_gt, info, seed, overlap) in enumerate(
        _pairs(name, args.fragments, args.limit, args.cut_dirs), 1
    ):
        T, verdict, found, seconds, kind = runner.register(refs, seed, T_gt)
        record = _record(
            pair, T, T_gt, info, verdict, found, seconds, features=kind, overlap=overlap
        )
        if name == "cut":  # cut_pairs.py's criterion on the source's points
            from cut_pairs import judged

            folder = Path(refs[0][0]).resolve().parent  # a cut pair's folder, in its root
            source = f"{folder.name}/{Path(refs[0][0]).name}"
            summary = {"source": source, "T_tgt_src": T.tolist(), "passed": record["passed"]}
            record["right"] = judged(summary, folder.parent)["right"]
        records.append(record)
        if n % 10 == 0:
            print(f"  {name}: {n} pairs, {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return records


def _slid(r: dict) -> bool:
    """A slide: the rotation right, the translation off by half a metre or more."""
    return r["rotation_error_deg"] < DEG and r["translation_error_m"] >= 0.5


def table(by_set: dict[str, list[dict]]) -> None:
    """Print the bands, the sweep, the passing wrong results and the seconds."""
    bands = [
        (band, [r for s in sets for r in by_set.get(s, [])])
        for band, sets in BANDS.items()
        if any(s in by_set for s in sets)
    ]
    print("| band | pairs | pass the gate | right | wrong (slid) |")
    print("|---|---|---|---|---|")
    for band, records in bands:
        passed = [r for r in records if r["passed"]]
        wrong = [r for r in passed if not r["right"]]
        print(
            f"| {band} | {len(records)} | {len(passed)} | {len(passed) - len(wrong)} | "
            f"{len(wrong)} ({sum(map(_slid, wrong))}) |"
        )
    print("\nCue at or above the threshold, among the results that pass the gate: wrong ones")
    print("caught / wrong, right ones lost / right\n")
    print("| cue >= | " + " | ".join(band for band, _ in bands) + " |")
    print("|---|" + "---|" * len(bands))
    for cue, thresholds in SWEEP.items():
        for threshold in thresholds:
            cells = []
            for _, records in bands:
                passed = [r for r in records if r["passed"]]
                wrong = [r for r in passed if not r["right"]]
                right = [r for r in passed if r["right"]]
                caught = sum(r[cue] >= threshold for r in wrong)
                lost = sum(r[cue] >= threshold for r in right)
                cells.append(f"{caught}/{len(wrong)}, lost {lost}/{len(right)}")
            print(f"| {cue} {threshold:g} | " + " | ".join(cells) + " |")
    for rule in EITHER:
        cells = []
        for _, records in bands:
            passed = [r for r in records if r["passed"]]
            fires = [any(r[c] >= t for c, t in rule) for r in passed]
            caught = sum(f and not r["right"] for f, r in zip(fires, passed, strict=True))
            lost = sum(f and r["right"] for f, r in zip(fires, passed, strict=True))
            wrong = sum(not r["right"] for r in passed)
            cells.append(f"{caught}/{wrong}, lost {lost}/{len(passed) - wrong}")
        label = " or ".join(f"{c} {t:g}" for c, t in rule)
        print(f"| {label} | " + " | ".join(cells) + " |")
    print("\nPassing results (wrong first), cues:")
    shown = ("seq_ratio", "seq_voxels", "seq_far_ratio", "seq_far_voxels", "ref_ratio",
             "ref_overlap_ratio", "ref_voxels", "slide_voxels", "restart_gain",
             "truth_inliers", "result_inliers")  # fmt: skip
    for band, records in bands:
        passed = sorted((r for r in records if r["passed"]), key=lambda r: (r["right"], r["name"]))
        for r in passed:
            values = " ".join(f"{c}={r.get(c, float('nan')):.2f}" for c in shown)
            print(
                f"  {band[:8]:8s} {'right' if r['right'] else 'WRONG'} {r['name']:36s} "
                f"{r['features']:5s} conf {r['confidence']:.2f} "
                f"{r['rotation_error_deg']:6.1f} deg {r['translation_error_m']:5.2f} m  {values}"
            )
    print("\n| band | wrong results | the result explains more correspondences than the truth |")
    print("|---|---|---|")
    for band, records in bands:
        wrong = [r for r in records if not r["right"] and "result_inliers" in r]
        more = sum(r["result_inliers"] > r["truth_inliers"] for r in wrong)
        print(f"| {band} | {len(wrong)} | {more} |")
    print("\n| band | cue s / pair (median, max) | registration s / pair (median) |")
    print("|---|---|---|")
    for band, records in bands:
        cue_s = [r["cue_seconds"] for r in records]
        print(
            f"| {band} | {statistics.median(cue_s):.2f}, {max(cue_s):.2f} | "
            f"{statistics.median(r['seconds'] for r in records):.2f} |"
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--fragments", type=Path, default=None)
    parser.add_argument("--cache-dir", type=Path, default=None)
    parser.add_argument("--sets", nargs="+", default=[s for s in SETS if s != "cut"], choices=SETS)
    parser.add_argument("--limit", type=int, default=None, help="first N pairs of each set")
    parser.add_argument("--no-fallback", action="store_true", help="no FPFH second opinion")
    parser.add_argument("--table-only", action="store_true")
    parser.add_argument("--cut-dirs", type=Path, nargs="+", default=[], help="cut_pairs.py sets")
    args = parser.parse_args()
    if "cut" in args.sets and not args.table_only and not args.cut_dirs:
        parser.error("--sets cut needs --cut-dirs (folders of cut_pairs.py make)")
    dev = [s for s in args.sets if s.startswith("dev-")]
    if dev and not args.table_only and (args.fragments is None or not args.fragments.is_dir()):
        parser.error(f"--fragments {args.fragments}: no such folder (the sets {' '.join(dev)})")
    args.out.mkdir(parents=True, exist_ok=True)
    runner: list = [None]
    by_set = {}
    for name in args.sets:
        limit = f"-limit{args.limit}" if args.limit else ""
        fallback = "-nofallback" if args.no_fallback else ""
        out = args.out / f"ambiguity-{name}{limit}{fallback}.json"
        if not out.exists():
            if args.table_only:
                continue
            print(f"running {name}", file=sys.stderr, flush=True)
            out.write_text(json.dumps(_run(name, args, runner), indent=1) + "\n")
        by_set[name] = json.loads(out.read_text())
    if by_set:
        table(by_set)
    return 0


if __name__ == "__main__":
    sys.exit(main())
