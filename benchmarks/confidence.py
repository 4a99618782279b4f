"""The development set of the confidence gate: register many pairs, keep every cue, fit.

`collect` registers every pair of the development set with the CLI's defaults (the Python API,
`voxel_size="auto"`), judges each result against the ground truth and appends one JSON line
per pair (its cues, its errors, right or wrong) to OUT.jsonl; a rerun skips the pairs already
there. The set, made at run time from ../shared/data:

* posed RGB-D pairs at many frame distances, wide ones included (most of the failures):
  tum_fr1_desk_full, tum_fr3_cabinet, realsense_tabletop, tum_fr1_rpy, tum_fr1_desk;
* every pair among the five fragments of the 3DMatch sample with ground truth (3DMatch and
  3DLoMatch records); the two pairs in neither file overlap by less than 10 %: negatives;
* the demo pair and the sample's 3DMatch pairs scaled by 0.01 and 100, thinned to 1/2 and 1/4
  (both clouds, or the source alone), with noise of 0.25 and 0.5 voxel;
* pairs that cannot be right: uniform noise onto a cloud, noise onto noise, a plane onto a
  plane, depth frames of two different rooms.

Right means within 5 deg and 10 cm (times the scale of a scaled copy).

`fit` fits the probability that a result is right (logistic regression on the cues,
:mod:`byoc_cli.pipeline.confidence`), by sequence-grouped cross-validation prints precision
and recall of exit 0 at each threshold and a reliability diagram, and prints the coefficients
and the threshold for at least 99 % precision.

Usage:
    python benchmarks/confidence.py collect --out dev.jsonl [--part I/N]
    python benchmarks/confidence.py fit dev.jsonl [more.jsonl ...]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from any_scan import errors, make  # the same copies and the same judge as any_scan.py

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
RGBD = DATA / "rgbd"
SAMPLE = DATA / "3dmatch" / "sample"
BENCH = DATA / "3dmatch" / "benchmarks"
#: (sequence, frame distances)
RGBD_SETS = (
    ("tum_fr1_desk_full", (10, 20, 40, 60)),
    ("tum_fr3_cabinet", (1, 2, 4, 8)),
    ("realsense_tabletop", (5, 15, 25)),
    ("tum_fr1_rpy", (20, 60)),
    ("tum_fr1_desk", (2, 4)),
)
ROT_DEG, TRANS_M = 5.0, 0.10
#: a wrong result that is not a near miss: beyond 15 deg or 30 cm (or no right answer)
GROSS_DEG, GROSS_M = 15.0, 0.30
#: the share of right results the default threshold keeps
RECALL = 0.95


def _gross(record: dict) -> bool:
    if record["right"]:
        return False
    if "rot_deg" not in record:
        return True
    return record["rot_deg"] > GROSS_DEG or record["trans_m"] > GROSS_M


def rgbd_pairs() -> Iterator[tuple[str, str, object, object, np.ndarray | None, float]]:
    """``(name, group, load_source, load_target, T_gt, scale)`` of the posed sequences."""
    from byoc_cli.evaluation.pairs import rgbd_pairs as make

    for sequence, spacings in RGBD_SETS:
        for spacing in spacings:
            pairs, _ = make([RGBD / sequence], spacing=spacing)
            for p in pairs:
                yield f"{p.name}@{spacing}", sequence, p.source.load, p.target.load, p.T_gt, 1.0


def _fragment(k: int) -> np.ndarray:
    from byoc_cli.api import load_cloud

    return load_cloud(SAMPLE / "3DMatch" / "7-scenes-redkitchen" / f"cloud_bin_{k}.ply")


def fragment_pairs() -> Iterator[tuple]:
    """Every pair of the sample's five fragments: ground truth, or none (< 10 % overlap)."""
    from byoc_cli.io.threedmatch import read_gt_log

    truth = {}
    for bench in ("3DMatch", "3DLoMatch"):
        for rec in read_gt_log(BENCH / bench / "7-scenes-redkitchen" / "gt.log"):
            truth[(rec.i, rec.j)] = rec.T_tgt_src
    frags = (0, 4, 7, 21, 34)
    for a in range(len(frags)):
        for b in range(a + 1, len(frags)):
            i, j = frags[a], frags[b]
            T = truth.get((i, j))
            yield (
                f"kitchen:{i}-{j}",
                "kitchen",
                lambda j=j: _fragment(j),
                lambda i=i: _fragment(i),
                T,
                1.0,
            )


def variant_pairs() -> Iterator[tuple]:
    """Scaled, thinned and noisy copies of the demo pair and the 3DMatch sample pairs."""
    from byoc_cli.api import load_cloud

    demo = DATA / "pairs" / "3dmatch_demo"
    bases = [
        (
            "demo",
            lambda: load_cloud(demo / "source.ply"),
            lambda: load_cloud(demo / "target.ply"),
            np.loadtxt(demo / "T_gt.txt"),
        )
    ]
    for name, _, src, tgt, T, _ in fragment_pairs():
        if T is not None and name in ("kitchen:0-4", "kitchen:4-7", "kitchen:7-21"):
            bases.append((name, src, tgt, T))
    recipes = [("x0.01", {"scale": 0.01}), ("x100", {"scale": 100.0})]
    for k in (2, 4):
        recipes += [(f"thin{k}both", {"thin": k, "both": True})]
        recipes += [(f"thin{k}src", {"thin": k, "both": False})]
    recipes += [("noise0.25", {"noise": 0.25}), ("noise0.5", {"noise": 0.5})]
    for n, (name, src, tgt, T) in enumerate(bases):
        for label, recipe in recipes:

            def load(which, src=src, tgt=tgt, recipe=recipe, seed=n):
                return make(src(), tgt(), recipe, seed)[which]

            s = recipe.get("scale", 1.0)
            yield (
                f"{name}~{label}",
                "variants",
                lambda load=load: load(0),
                lambda load=load: load(1),
                T,
                s,
            )


def negative_pairs() -> Iterator[tuple]:
    """Pairs with no right answer: noise, planes, two different rooms."""
    from byoc_cli.evaluation.pairs import rgbd_pairs as make

    rng = np.random.default_rng(7)

    def noise(n=20000, size=3.0):
        return rng.uniform(0, size, (n, 3))

    def plane(n=20000, size=3.0):
        xy = rng.uniform(0, size, (n, 2))
        return np.column_stack([xy, 0.002 * rng.standard_normal(n)])

    frag = lambda: _fragment(0)  # noqa: E731
    for k in range(3):
        yield f"noise-onto-cloud:{k}", "negative", noise, frag, None, 1.0
        yield f"noise-onto-noise:{k}", "negative", noise, noise, None, 1.0
        yield f"plane-onto-plane:{k}", "negative", plane, plane, None, 1.0
        yield f"cloud-onto-noise:{k}", "negative", frag, noise, None, 1.0
    desk, _ = make([RGBD / "tum_fr1_desk_full"], spacing=30)
    cabinet, _ = make([RGBD / "tum_fr3_cabinet"], spacing=6)
    tabletop, _ = make([RGBD / "realsense_tabletop"], spacing=10)
    for n, (a, b) in enumerate(zip(desk, cabinet, strict=False)):
        yield f"desk-onto-cabinet:{n}", "negative", a.source.load, b.target.load, None, 1.0
    for n, (a, b) in enumerate(zip(tabletop, cabinet, strict=False)):
        yield f"tabletop-onto-cabinet:{n}", "negative", a.source.load, b.target.load, None, 1.0


def collect(out: Path, features: str, part: tuple[int, int], groups: list[str]) -> None:
    from byoc_cli.api import Registrar

    done = set()
    if out.exists():
        done = {json.loads(line)["name"] for line in out.read_text().splitlines() if line}
    registrar = Registrar(features, device="cpu")
    sources = (rgbd_pairs(), fragment_pairs(), variant_pairs(), negative_pairs())
    count = -1
    with out.open("a") as file:
        for source in sources:
            for name, group, load_src, load_tgt, T_gt, scale in source:
                count += 1
                if name in done or count % part[1] != part[0] - 1:
                    continue
                if groups and group not in groups:
                    continue
                record = {"name": name, "group": group, "features": features, "scale": scale}
                start = time.perf_counter()
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        result = registrar.register(load_src(), load_tgt())
                except Exception as exc:  # a refusal: never exit 0, nothing to calibrate
                    record.update(refused=str(exc), right=False)
                else:
                    record.update(cues=result.cues, confidence=result.confidence)
                    record["voxel"] = result.voxel_size / scale
                    if T_gt is None:
                        record["right"] = False
                    else:
                        T_gt = np.array(T_gt, dtype=np.float64)
                        T_gt[:3, 3] *= scale
                        rot, trans = errors(result.T_tgt_src, T_gt)
                        record.update(rot_deg=rot, trans_m=trans / scale)
                        record["right"] = rot < ROT_DEG and trans / scale < TRANS_M
                record["seconds"] = time.perf_counter() - start
                file.write(json.dumps(record) + "\n")
                file.flush()
                print(
                    f"{name:40s} right={record['right']!s:5s} "
                    f"p={record.get('confidence', float('nan')):.3f}",
                    flush=True,
                )


def fit(paths: list[Path]) -> None:
    from byoc_cli.pipeline.confidence import FEATURES, cue_matrix, fit_logistic, sigmoid

    records = {}  # a later file's record of a pair replaces an earlier one
    for p in paths:
        for line in p.read_text().splitlines():
            if line:
                records[json.loads(line)["name"]] = json.loads(line)
    records = list(records.values())
    scored = [r for r in records if "cues" in r]
    refused = [r for r in records if "refused" in r]
    X = cue_matrix([r["cues"] for r in scored])
    y = np.array([r["right"] for r in scored], dtype=np.float64)
    groups = np.array([r["group"] for r in scored])
    print(
        f"{len(records)} pairs: {len(scored)} registered ({int(y.sum())} right), "
        f"{len(refused)} refused"
    )
    # out-of-group predictions: each group scored by a model fitted without it
    p_cv = np.zeros(len(y))
    for g in np.unique(groups):
        held = groups == g
        w = fit_logistic(X[~held], y[~held])
        p_cv[held] = sigmoid(X[held] @ w[:-1] + w[-1])
    w = fit_logistic(X, y)
    print("coefficients (features, then bias):")
    for name, value in zip([*FEATURES, "bias"], w, strict=True):
        print(f"    {name:22s} {value:+.4f}")
    gross = np.array([_gross(r) for r in scored])
    print(
        "\nthreshold  precision  recall  gross-free  (grouped cross-validation; exit 0 = p >= "
        "threshold; gross-free: share of exit 0 within 15 deg and 30 cm)"
    )
    best = None
    for t in np.round(np.arange(0.05, 1.0, 0.05), 2):
        passed = p_cv >= t
        tp = float((passed & (y == 1)).sum())
        precision = tp / max(passed.sum(), 1)
        recall = tp / max(y.sum(), 1)
        clean = 1.0 - float((passed & gross).sum()) / max(passed.sum(), 1)
        print(f"  {t:.2f}     {100 * precision:6.2f}    {100 * recall:6.2f}    {100 * clean:6.2f}")
        if recall >= RECALL:
            best = (float(t), precision, recall, clean)
    print(f"\nthe highest threshold that keeps {100 * RECALL:g} % of the right results:", best)
    print("\nreliability (cross-validated p, bins of 0.1): bin  pairs  predicted  right")
    for lo in np.arange(0, 1.0, 0.1):
        inside = (p_cv >= lo) & (p_cv < lo + 0.1 + (1e-9 if lo >= 0.9 else 0))
        if inside.any():
            print(
                f"  {lo:.1f}-{lo + 0.1:.1f}  {int(inside.sum()):5d}   "
                f"{p_cv[inside].mean():.3f}     {y[inside].mean():.3f}"
            )
    worst = sorted(zip(p_cv, y, [r["name"] for r in scored], strict=True), reverse=True)
    print("\nwrong results with the highest cross-validated p:")
    for p, _, name in [t for t in worst if t[1] == 0][:8]:
        print(f"  {p:.3f} {name}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--features", default="byoc")
    c.add_argument("--part", default="1/1", help="I/N: every N-th pair from the I-th")
    c.add_argument("--groups", nargs="*", default=[], help="only these groups (default: all)")
    f = sub.add_parser("fit")
    f.add_argument("paths", type=Path, nargs="+")
    args = parser.parse_args(argv)
    if args.command == "collect":
        part = tuple(int(x) for x in args.part.split("/"))
        collect(args.out, args.features, part, args.groups)
    else:
        fit(args.paths)
    return 0


if __name__ == "__main__":
    sys.exit(main())
