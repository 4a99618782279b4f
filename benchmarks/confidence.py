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
    python benchmarks/confidence.py collect --out coarse.jsonl --refine none \
        --truth-from dev.jsonl
    python benchmarks/confidence.py fit dev.jsonl [more.jsonl ...] [--checked check.jsonl]
    python benchmarks/confidence.py check-truth dev.jsonl [more.jsonl ...] --out check.jsonl \
        [--part I/N]
    python benchmarks/confidence.py agreement dev.jsonl ... --coarse coarse.jsonl ... \
        [--checked check.jsonl ...]
    python benchmarks/confidence.py floor --out floor.jsonl [--part I/N]
    python benchmarks/confidence.py floor-table floor.jsonl [more.jsonl ...]

`check-truth` refines every pair's ground truth a second time, with Open3D's multiscale
point-to-plane ICP instead of byoc's (the first refinement is the collection's
``T_gt_refined``). `fit --checked` then also scores the gate on the pairs whose truth the data
determine: the two refinements agree within a quarter of the thresholds. Where they do not
(the clouds' planes leave the pose free to slide, for one), right and wrong at 5 deg and
10 cm are not known, and those pairs are left out of that second table (not of the fit).

`agreement` counts, per group, the learned results that agree with FPFH's unrefined result of
the same pair (from a `collect --refine none` collection; within AGREE_DEG and AGREE_M) and
those that do not, right and wrong: how much a second opinion of other features says.

`floor` registers every pair as `byoc register` does (the FPFH fallback included) and, for
each refined registration, also without the refinement's restarts: the confidence before the
restarts (with their most confident cues) against after, and the seconds the restarts took.
`floor-table` prints, for each floor, how many registrations would skip the restarts and
whether any of them would have reached the default gate after them (the choice of
`register.RESTART_FLOOR`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from collections import Counter
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
    ("tum_fr1_desk_full", (10, 20, 30, 40, 50, 60)),
    ("tum_fr3_cabinet", (1, 2, 4, 8)),
    ("realsense_tabletop", (5, 15, 25, 35)),
    ("tum_fr1_rpy", (20, 60)),
    ("tum_fr1_desk", (2, 4, 8)),
)
ROT_DEG, TRANS_M = 5.0, 0.10
#: a wrong result that is not a near miss: beyond 15 deg or 30 cm (or no right answer)
GROSS_DEG, GROSS_M = 15.0, 0.30
#: FPFH runs on the pairs whose learned confidence is below this (the fallback runs below the
#: gate, under 0.5 with any model fitted so far)
FALLBACK_MARGIN = 0.7
#: the share of right results the default threshold keeps
RECALL = 0.95
#: a pair's truth is determined when its two refinements agree within these (a quarter of the
#: thresholds; metres times the pair's scale)
CHECK_DEG, CHECK_M = ROT_DEG / 4, TRANS_M / 4
#: a learned result agrees with FPFH's when they are this close (metres times the pair's scale)
AGREE_DEG, AGREE_M = 10.0, 0.30
#: the levels of the second refinement (Open3D's point-to-plane ICP): voxel (metres times the
#: pair's scale) and iterations; correspondences within 1.5 voxels
CHECK_LEVELS = ((0.04, 40), (0.02, 40), (0.01, 40))


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
    recipes = [(f"x{s:g}", {"scale": s}) for s in (0.01, 0.1, 10.0, 100.0)]
    recipes += [("thin8both", {"thin": 8, "both": True})]
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


def _result(registrar, src: np.ndarray, tgt: np.ndarray, **settings) -> dict:
    """One registration's record: its transform, cues, confidence and seconds (or refusal)."""
    start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = registrar.register(src, tgt, **settings)
    except Exception as exc:  # a refusal: never exit 0, nothing to calibrate
        return {"refused": str(exc), "seconds": time.perf_counter() - start}
    return {
        "T": result.T_tgt_src.tolist(),
        "cues": result.cues,
        "confidence": result.confidence,
        "voxel": result.voxel_size,
        "seconds": time.perf_counter() - start,
    }


def _refined_truth(registrar, src, tgt, T_gt: np.ndarray) -> np.ndarray:
    """The ground truth refined by the multiscale ICP on the full clouds: the alignment the
    data support near the truth (as FCGF refines KITTI's GPS poses with ICP)."""
    import torch

    from byoc_cli.pipeline.refine import refine_multiscale

    choice = registrar.choose_voxel(src, tgt)
    refined = refine_multiscale(
        torch.from_numpy(src), torch.from_numpy(tgt), torch.from_numpy(T_gt), choice.refine_voxel
    )
    return refined.T_tgt_src.numpy()


def _truths(paths: list[Path]) -> dict[str, dict]:
    """The ground truth of every pair of earlier collections, by name."""
    keys = ("T_gt", "T_gt_refined", "T_gt_refined_error")
    return {r["name"]: {k: r[k] for k in keys if k in r} for r in _load(paths)}


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
    records = {r["name"]: r for r in _load(paths) if r.get("T_gt") is not None}
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


def _with_checks(records: list[dict], checked: list[Path] | None) -> list[dict]:
    """``records``, each given its second refinement (``T_gt_open3d``) from the
    :func:`check_truth` files ``checked``, where they have one."""
    second = {r["name"]: r["T_gt_open3d"] for r in _load(checked or [])}
    for r in records:
        if r["name"] in second:
            r["T_gt_open3d"] = second[r["name"]]
    return records


def determined(record: dict) -> bool:
    """Whether right and wrong are known for ``record``: it has no truth (nothing can be
    right), or both refinements of its truth exist and agree within CHECK_DEG and CHECK_M."""
    if record.get("T_gt") is None:
        return True
    if "T_gt_refined" not in record or "T_gt_open3d" not in record:
        return False
    rot, trans = errors(np.array(record["T_gt_refined"]), np.array(record["T_gt_open3d"]))
    return rot <= CHECK_DEG and trans / record["scale"] <= CHECK_M


def part_of_set(part: tuple[int, int]) -> Iterator[tuple]:
    """The pairs of the set (:func:`rgbd_pairs` and the rest, in order) of part ``(I, N)``:
    every N-th from the I-th."""
    sources = (rgbd_pairs(), fragment_pairs(), variant_pairs(), negative_pairs())
    for count, pair in enumerate(p for source in sources for p in source):
        if count % part[1] == part[0] - 1:
            yield pair


def collect(
    out: Path,
    part: tuple[int, int],
    groups: list[str],
    refine: str | None = None,
    truth_from: list[Path] | None = None,
) -> None:
    """Register the pairs into ``out``; ``refine="none"``: both features unrefined, FPFH on
    every pair (the calibration of results that are not refined); ``truth_from``: earlier
    collections whose ground truth (refined on the data) is reused."""
    from byoc_cli.api import Registrar

    done = set()
    if out.exists():
        done = {json.loads(line)["name"] for line in out.read_text().splitlines() if line}
    truths = _truths(truth_from) if truth_from else {}
    settings = {} if refine is None else {"refine": refine}
    byoc = Registrar("byoc", device="cpu", fallback=None)
    fpfh = Registrar("fpfh", device="cpu")
    with out.open("a") as file:
        for name, group, load_src, load_tgt, T_gt, scale in part_of_set(part):
            if name in done or (groups and group not in groups):
                continue
            record = {"name": name, "group": group, "scale": scale}
            src, tgt = load_src(), load_tgt()
            record["byoc"] = _result(byoc, src, tgt, **settings)
            # FPFH with the learned path's refinement: what the fallback runs, which it
            # does only below the gate (with a margin for the refitted model)
            if refine is not None:
                record["fpfh"] = _result(fpfh, src, tgt, **settings)
            elif record["byoc"].get("confidence", 0.0) < FALLBACK_MARGIN:
                record["fpfh"] = _result(fpfh, src, tgt, refine="multiscale")
            else:
                record["fpfh"] = {"skipped": f"learned confidence >= {FALLBACK_MARGIN}"}
            if name in truths:
                record.update(truths[name])
            elif T_gt is not None:
                T_gt = np.array(T_gt, dtype=np.float64)
                T_gt[:3, 3] *= scale
                record["T_gt"] = T_gt.tolist()
                try:
                    record["T_gt_refined"] = _refined_truth(byoc, src, tgt, T_gt).tolist()
                except Exception as exc:
                    record["T_gt_refined_error"] = str(exc)
            file.write(json.dumps(record) + "\n")
            file.flush()
            print(
                f"{name:40s} "
                + " ".join(
                    f"{k}={record[k].get('confidence', float('nan')):.3f}" for k in ("byoc", "fpfh")
                ),
                flush=True,
            )


KINDS = ("byoc", "fpfh")


def _load(paths: list[Path]) -> list[dict]:
    records = {}  # a later file's record of a pair replaces an earlier one
    for p in paths:
        for line in p.read_text().splitlines():
            if line:
                records[json.loads(line)["name"]] = json.loads(line)
    return list(records.values())


def _judge(record: dict, kind: str, truth: str) -> dict | None:
    """``kind``'s result of a pair judged against ``truth`` (``"gt"`` or ``"refined"``);
    None when it was refused."""
    result = record[kind]
    if "cues" not in result:
        return None
    T_true = record.get("T_gt_refined" if truth == "refined" else "T_gt", record.get("T_gt"))
    if T_true is None:
        return {"right": False, "gross": True}
    rot, trans = errors(np.array(result["T"]), np.array(T_true))
    trans /= record["scale"]
    return {
        "right": rot < ROT_DEG and trans < TRANS_M,
        "gross": rot > GROSS_DEG or trans > GROSS_M,
    }


def _cross_validated(records: list[dict], kind: str, truth: str):
    """Out-of-group probabilities of ``kind``'s results (nan where refused), the labels and
    the coefficients fitted on all."""
    from byoc_cli.pipeline.confidence import cue_matrix, fit_logistic, sigmoid

    judged = [_judge(r, kind, truth) for r in records]
    have = np.array([j is not None for j in judged])
    X = cue_matrix([r[kind]["cues"] for r, j in zip(records, judged, strict=True) if j])
    y = np.array([j["right"] for j in judged if j], dtype=np.float64)
    groups = np.array([r["group"] for r, j in zip(records, judged, strict=True) if j])
    p = np.zeros(len(y))
    for g in np.unique(groups):
        held = groups == g
        w = fit_logistic(X[~held], y[~held])
        p[held] = sigmoid(X[held] @ w[:-1] + w[-1])
    p_all = np.full(len(records), np.nan)
    p_all[have] = p
    return p_all, judged, fit_logistic(X, y)


def _policy(p_byoc, p_fpfh, judged_byoc, judged_fpfh, threshold: float, fallback: bool):
    """Per pair: (confidence, right, gross) of what the default returns (None: refused)."""
    out = []
    for pb, pf, jb, jf in zip(p_byoc, p_fpfh, judged_byoc, judged_fpfh, strict=True):
        pick = (pb, jb) if jb is not None else (-1.0, None)
        if fallback and not pick[0] >= threshold and jf is not None and pf > pick[0]:
            pick = (pf, jf)
        out.append(None if pick[1] is None else (pick[0], pick[1]["right"], pick[1]["gross"]))
    return out


def _table(records, p_byoc, p_fpfh, judged_byoc, judged_fpfh, fallback: bool):
    print(
        "threshold  precision  recall  gross-free  right  exit0  (grouped cross-validation; "
        "recall: of the pairs whose returned transform is right)"
    )
    best = None
    for t in np.round(np.arange(0.05, 1.0, 0.05), 2):
        picks = [x for x in _policy(p_byoc, p_fpfh, judged_byoc, judged_fpfh, t, fallback) if x]
        passed = np.array([c >= t for c, _, _ in picks])
        right = np.array([r for _, r, _ in picks])
        gross = np.array([g for _, _, g in picks])
        tp = float((passed & right).sum())
        precision = tp / max(passed.sum(), 1)
        recall = tp / max(right.sum(), 1)
        clean = 1.0 - float((passed & gross).sum()) / max(passed.sum(), 1)
        print(
            f"  {t:.2f}     {100 * precision:6.2f}    {100 * recall:6.2f}    {100 * clean:6.2f}"
            f"  {int(right.sum()):5d}  {int(passed.sum()):5d}"
        )
        if recall >= RECALL:
            best = (float(t), round(precision, 4), round(recall, 4), round(clean, 4))
    print(f"the highest threshold that keeps {100 * RECALL:g} % of the right results:", best)
    return best


def fit(paths: list[Path], truth: str, checked: list[Path] | None = None) -> None:
    from byoc_cli.pipeline.confidence import FEATURES

    records = _with_checks(_load(paths), checked)
    print(f"{len(records)} pairs, judged against {truth} truth")
    moved = [r for r in records if "T_gt_refined" in r]
    shifts = [errors(np.array(r["T_gt_refined"]), np.array(r["T_gt"])) for r in moved]
    far = [
        (r["name"], rot, tr / r["scale"])
        for r, (rot, tr) in zip(moved, shifts, strict=True)
        if rot > 2.0 or tr / r["scale"] > 0.04
    ]
    print(
        f"ground truth refined on the data: {len(far)} of {len(moved)} moved beyond 2 deg or 4 cm:",
        ", ".join(f"{n} ({a:.1f} deg, {100 * b:.1f} cm)" for n, a, b in far[:12]),
        "..." if len(far) > 12 else "",
    )
    ps, judged = {}, {}
    for kind in KINDS:
        ps[kind], judged[kind], w = _cross_validated(records, kind, truth)
        n = sum(j is not None for j in judged[kind])
        right = sum(bool(j and j["right"]) for j in judged[kind])
        print(f"\n{kind}: {n} registered ({right} right), {len(records) - n} refused")
        print("coefficients (features, then bias):")
        print("    (" + ", ".join(f"{v:.4f}" for v in w) + ")")
        for name, value in zip([*FEATURES, "bias"], w, strict=True):
            print(f"    {name:22s} {value:+.4f}")
    policies = [
        ("learned only", "byoc", False),
        ("learned, then FPFH below the threshold", "byoc", True),
    ]
    if all("skipped" not in r["fpfh"] for r in records):  # FPFH ran on every pair
        policies.append(("FPFH only", "fpfh", False))
    other = {"byoc": "fpfh", "fpfh": "byoc"}
    for title, kind, fallback in policies:
        print(f"\n== {title}")
        ps_, js_ = (ps[kind], ps[other[kind]]), (judged[kind], judged[other[kind]])
        best = _table(records, *ps_, *js_, fallback)
        if best is None:
            continue
        picks = _policy(*ps_, *js_, best[0], fallback)
        print("reliability at that threshold (bins of 0.1): bin  pairs  predicted  right")
        conf = np.array([x[0] for x in picks if x])
        right = np.array([x[1] for x in picks if x], dtype=np.float64)
        for lo in np.arange(0, 1.0, 0.1):
            inside = (conf >= lo) & (conf < lo + 0.1 + (1e-9 if lo >= 0.9 else 0))
            if inside.any():
                print(
                    f"  {lo:.1f}-{lo + 0.1:.1f}  {int(inside.sum()):5d}   "
                    f"{conf[inside].mean():.3f}     {right[inside].mean():.3f}"
                )
        wrong = sorted(
            (x[0], r["name"]) for x, r in zip(picks, records, strict=True) if x and not x[1]
        )
        print(
            "wrong results with the highest p:",
            ", ".join(f"{n} {p:.3f}" for p, n in wrong[::-1][:8]),
        )
    if checked:
        _determined_tables(records, ps, judged, policies)


def _determined_tables(records: list[dict], ps: dict, judged: dict, policies: list) -> None:
    """The precision and recall tables again, on the pairs whose truth the data determine
    (the fit and its cross-validation are those of all pairs)."""
    keep = np.array([determined(r) for r in records])
    left = Counter(r["group"] for r, k in zip(records, keep, strict=True) if not k)
    print(
        f"\n== pairs whose truth the data determine (its two refinements within {CHECK_DEG:g} deg"
        f" and {100 * CHECK_M:g} cm): {int(keep.sum())} of {len(records)}; left out, by group:",
        ", ".join(f"{g} {n}" for g, n in sorted(left.items())) or "none",
    )
    other = {"byoc": "fpfh", "fpfh": "byoc"}
    rows = np.flatnonzero(keep)
    sub = [records[i] for i in rows]
    for title, kind, fallback in policies:
        print(f"\n== {title}, determined truth only")
        pick = [[judged[k][i] for i in rows] for k in (kind, other[kind])]
        _table(sub, ps[kind][keep], ps[other[kind]][keep], *pick, fallback)


def agreement(paths: list[Path], coarse: list[Path], checked: list[Path] | None) -> None:
    """Per group: learned results that agree with FPFH's unrefined one, right and wrong, and
    those that do not (or where FPFH refused); with ``checked``, determined pairs only."""
    records = _with_checks(_load(paths), checked)
    fpfh = {r["name"]: r["fpfh"] for r in _load(coarse)}
    counts: dict[str, Counter] = {}
    for r in records:
        judged = _judge(r, "byoc", "refined")
        if judged is None or r["name"] not in fpfh or (checked and not determined(r)):
            continue
        other = fpfh[r["name"]]
        if "T" not in other:
            key = "fpfh refused"
        else:
            rot, trans = errors(np.array(r["byoc"]["T"]), np.array(other["T"]))
            key = "agree" if rot < AGREE_DEG and trans / r["scale"] < AGREE_M else "disagree"
        counts.setdefault(r["group"], Counter())[(key, judged["right"])] += 1
    total = sum(counts.values(), Counter())
    print(
        f"learned results against FPFH's unrefined ones (within {AGREE_DEG:g} deg and"
        f" {100 * AGREE_M:g} cm){', determined truth only' if checked else ''}: right / wrong"
    )
    print(f"{'group':22s} {'agree':>9s} {'disagree':>9s} {'refused':>9s}")
    for group, c in [*sorted(counts.items()), ("all", total)]:
        cells = [f"{c[(k, True)]}/{c[(k, False)]}" for k in ("agree", "disagree", "fpfh refused")]
        print(f"{group:22s} {cells[0]:>9s} {cells[1]:>9s} {cells[2]:>9s}")


def floor_collect(out: Path, part: tuple[int, int]) -> None:
    """Every pair's refined registrations with and without the restarts, one line per pair."""
    import dataclasses

    import byoc_cli.pipeline.register as register
    from byoc_cli.api import Registrar

    calls: list[dict] = []
    estimate = register.estimate_transform

    def both(src, tgt, config, voxel_size, clouds=None, refine_voxel=None, parallel=None):
        every = dataclasses.replace(config, restart_floor=0.0)  # the restarts always run
        after = estimate(src, tgt, every, voxel_size, clouds, refine_voxel, parallel)
        if config.refine == "multiscale" and config.restarts:
            none = dataclasses.replace(config, restarts=False)
            before = estimate(src, tgt, none, voxel_size, clouds, refine_voxel, parallel)
            calls.append(
                {
                    "model": config.confidence_model,
                    "before": before.confidence,
                    "after": after.confidence,
                    "restart_seconds": after.timings.get("restarts", 0.0),
                }
            )
        return after

    register.estimate_transform = both  # the registrar calls it through the module
    registrar = Registrar("byoc", device="cpu", fallback="fpfh")
    with out.open("w") as file:
        for name, group, load_src, load_tgt, _, _ in part_of_set(part):
            calls.clear()
            record = {"name": name, "group": group}
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    record["confidence"] = registrar.register(load_src(), load_tgt()).confidence
            except Exception as exc:  # a refusal: no registration to measure
                record["refused"] = str(exc)
            record["calls"] = list(calls)
            file.write(json.dumps(record) + "\n")
            file.flush()
            print(name, [(c["model"], round(c["before"], 3), round(c["after"], 3)) for c in calls])


def floor_table(paths: list[Path]) -> None:
    """For each floor: registrations below it before the restarts, the most confident of them
    after, how many passed the default gate after, and the restarts' seconds they took."""
    from byoc_cli.pipeline.confidence import DEFAULT_MIN_CONFIDENCE

    calls = [
        c for p in paths for line in p.read_text().splitlines() for c in json.loads(line)["calls"]
    ]
    raised = [c for c in calls if c["after"] > c["before"] + 1e-9]
    print(
        f"{len(calls)} refined registrations; the restarts raised the confidence of {len(raised)}"
        + (f", by at most {max(c['after'] - c['before'] for c in raised):.3f}" if raised else "")
    )
    print("floor  below  of  passed-after  most-after  restart-s-below  restart-s-all")
    total = sum(c["restart_seconds"] for c in calls)
    for floor in (0.05, 0.1, 0.2, 0.3, 0.45):
        below = [c for c in calls if c["before"] < floor]
        passed = sum(c["after"] >= DEFAULT_MIN_CONFIDENCE for c in below)
        most = max((c["after"] for c in below), default=0.0)
        seconds = sum(c["restart_seconds"] for c in below)
        print(
            f"{floor:5.2f} {len(below):6d} {len(calls):4d} {passed:13d} {most:11.3f}"
            f" {seconds:16.1f} {total:14.1f}"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--part", default="1/1", help="I/N: every N-th pair from the I-th")
    c.add_argument("--groups", nargs="*", default=[], help="only these groups (default: all)")
    c.add_argument(
        "--refine", choices=("none",), help="unrefined results of both features, every pair"
    )
    c.add_argument(
        "--truth-from", type=Path, nargs="*", help="reuse these collections' ground truth"
    )
    f = sub.add_parser("fit")
    f.add_argument("paths", type=Path, nargs="+")
    f.add_argument("--truth", choices=("gt", "refined"), default="refined")
    f.add_argument(
        "--checked", type=Path, nargs="*", help="check-truth output: also score determined pairs"
    )
    a = sub.add_parser("agreement")
    a.add_argument("paths", type=Path, nargs="+")
    a.add_argument("--coarse", type=Path, nargs="+", required=True)
    a.add_argument("--checked", type=Path, nargs="*")
    k = sub.add_parser("check-truth")
    k.add_argument("paths", type=Path, nargs="+")
    k.add_argument("--out", type=Path, required=True)
    k.add_argument("--part", default="1/1", help="I/N: every N-th pair from the I-th")
    g = sub.add_parser("floor")
    g.add_argument("--out", type=Path, required=True)
    g.add_argument("--part", default="1/1", help="I/N: every N-th pair from the I-th")
    t = sub.add_parser("floor-table")
    t.add_argument("paths", type=Path, nargs="+")
    args = parser.parse_args(argv)
    part = tuple(int(x) for x in getattr(args, "part", "1/1").split("/"))
    if args.command in ("floor", "check-truth") and args.out.exists():  # never write over it
        parser.error(f"--out {args.out}: exists; give a new file")
    if args.command == "collect":
        collect(args.out, part, args.groups, args.refine, args.truth_from)
    elif args.command == "floor":
        floor_collect(args.out, part)
    elif args.command == "floor-table":
        floor_table(args.paths)
    elif args.command == "agreement":
        agreement(args.paths, args.coarse, args.checked)
    elif args.command == "check-truth":
        check_truth(args.paths, args.out, part)
    else:
        fit(args.paths, args.truth, args.checked)
    return 0


if __name__ == "__main__":
    sys.exit(main())
