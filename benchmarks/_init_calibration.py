"""`init.py collect` and `init.py fit`: the calibration of the local registration's confidence
(:mod:`byoc_cli.pipeline.local_confidence`).

`collect` registers the pairs of CALIBRATION_SETS from guesses perturbed from their ground
truth, in process with the Python API (`Registrar.register(..., init=T)`, the CLI's defaults):
per pair POSITIVES guesses at 0-15 deg / 0-40 cm (what a pipeline's pose gives; mostly right)
and HARD guesses at 30-60 deg / 0.5-1 m (mostly wrong: the refinement stops in another
basin). One JSON line per registration: its cues, transform, errors and label.

`fit` fits the logistic model on the cues (:func:`byoc_cli.pipeline.confidence.fit_logistic`),
by sequence-grouped cross-validation (each sequence's registrations judged by a model fitted
on the others) prints precision and recall of "passes the gate" at each threshold, the
reliability of the probabilities and the coefficients fitted on all, to paste into
``local_confidence.COEFFICIENTS``.

Right means within 5 deg and 10 cm of the truth: the ground truth refined on the data where
our refinement and Open3D's agree (`_init_pairs.refined_truth`), else the ground truth.
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import numpy as np

from _init_pairs import CALIBRATION_SETS, errors, perturbed, refined_truth, rgbd_pairs

#: guesses per pair: near ones (degrees, metres drawn uniformly) and hard ones
POSITIVES, HARD = 3, 2
NEAR = ((0.0, 15.0), (0.0, 0.40))
FAR = ((30.0, 60.0), (0.50, 1.00))
#: right within these (metres: depth-camera data)
RIGHT_DEG, RIGHT_M = 5.0, 0.10
#: every N-th pair of a set with more than this many pairs (bounded time)
MAX_PER_SET = 8


def _sets_pairs():
    for sequence, gap in CALIBRATION_SETS:
        found = list(rgbd_pairs(((sequence, gap),)))
        step = max(1, -(-len(found) // MAX_PER_SET))
        yield from found[::step]


def collect(out: Path, seed: int = 0) -> None:
    """Append the calibration's registrations to ``out`` (a rerun skips the pairs there)."""
    from byoc_cli.api import Registrar

    done = set()
    if out.exists():
        done = {json.loads(line)["pair"] for line in out.read_text().splitlines() if line}
    registrar = Registrar(device="cpu")
    rng = np.random.default_rng(seed)
    with out.open("a") as file:
        for pair in _sets_pairs():
            draws = [_draw(rng, NEAR) for _ in range(POSITIVES)]
            draws += [_draw(rng, FAR) for _ in range(HARD)]
            if pair.name in done:
                continue
            src, tgt = pair.load_source(), pair.load_target()
            voxel = registrar.choose_voxel(src, tgt).refine_voxel
            truth, determined = refined_truth(src, tgt, pair.T_gt, voxel)
            if not determined:
                truth = pair.T_gt
            centroid = src.mean(axis=0)
            for k, (deg, length) in enumerate(draws):
                T_init = perturbed(pair.T_gt, centroid, deg, length, rng)
                record = _run(registrar, src, tgt, T_init)
                record.update(pair=pair.name, group=pair.group, k=k, deg=deg, length=length)
                record.update(determined=determined, hard=k >= POSITIVES)
                if "T" in record:
                    rot, trans = errors(np.array(record["T"]), truth)
                    gt_rot, gt_trans = errors(np.array(record["T"]), pair.T_gt)
                    record.update(rot=rot, trans=trans, gt_rot=gt_rot, gt_trans=gt_trans)
                    record["right"] = rot < RIGHT_DEG and trans < RIGHT_M
                file.write(json.dumps(record) + "\n")
                file.flush()
            print(f"{pair.name:40s} determined={determined}", flush=True)


def _draw(rng, ranges) -> tuple[float, float]:
    (d0, d1), (m0, m1) = ranges
    return float(rng.uniform(d0, d1)), float(rng.uniform(m0, m1))


def _run(registrar, src, tgt, T_init) -> dict:
    start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = registrar.register(src, tgt, init=T_init)
    except Exception as exc:  # a refusal exits 1: nothing to calibrate
        return {"refused": str(exc)}
    return {
        "T": result.T_tgt_src.tolist(),
        "cues": result.cues,
        "confidence": result.confidence,
        "inside": result.init["inside_trust_region"],
        "seconds": time.perf_counter() - start,
    }


def _records(paths: list[Path]) -> list[dict]:
    out = []
    for path in paths:
        out += [json.loads(line) for line in path.read_text().splitlines() if line]
    return [r for r in out if "cues" in r]


def fit(paths: list[Path]) -> None:
    """Fit, cross-validate and print (the module docstring)."""
    from byoc_cli.pipeline.confidence import fit_logistic, sigmoid
    from byoc_cli.pipeline.local_confidence import FEATURES, local_cue_vector

    records = _records(paths)
    X = np.array([local_cue_vector(r["cues"]) for r in records])
    y = np.array([r["right"] for r in records], dtype=np.float64)
    groups = np.array([r["group"] for r in records])
    inside = np.array([r["inside"] for r in records])
    p = np.zeros(len(y))
    for g in np.unique(groups):
        held = groups == g
        w = fit_logistic(X[~held], y[~held])
        p[held] = sigmoid(X[held] @ w[:-1] + w[-1])
    zero = np.array([r["cues"]["fitness"] <= 0 for r in records])
    p[zero] = 0.0
    hard = np.array([r["hard"] for r in records])
    print(
        f"{len(records)} local registrations of {len({r['pair'] for r in records})} pairs "
        f"({int(y.sum())} right; {int(hard.sum())} from hard guesses, {int(y[hard].sum())} "
        "of them right)"
    )
    print("threshold  precision  recall  passed  wrong-passed  (grouped cross-validation,")
    print("           a result outside the trust region never passes)")
    for t in np.round(np.arange(0.05, 1.0, 0.05), 2):
        passed = (p >= t) & inside
        tp = float((passed & (y > 0)).sum())
        print(
            f"  {t:.2f}     {100 * tp / max(passed.sum(), 1):6.2f}    "
            f"{100 * tp / max(y.sum(), 1):6.2f}   {int(passed.sum()):5d}   "
            f"{int((passed & (y == 0)).sum()):5d}"
        )
    print("reliability (bins of 0.1): bin  registrations  predicted  right")
    for lo in np.arange(0, 1.0, 0.1):
        bin_ = (p >= lo) & (p < lo + 0.1 + (1e-9 if lo >= 0.9 else 0))
        if bin_.any():
            print(f"  {lo:.1f}-{lo + 0.1:.1f}  {int(bin_.sum()):5d}   {p[bin_].mean():.3f}  "
                  f"{y[bin_].mean():.3f}")  # fmt: skip
    wrong = sorted(((p[i], records[i]["pair"], records[i]["k"]) for i in range(len(y))
                    if not y[i] and inside[i]), reverse=True)[:8]  # fmt: skip
    print("wrong results inside the trust region with the highest p:",
          ", ".join(f"{n}#{k} {q:.3f}" for q, n, k in wrong))  # fmt: skip
    w = fit_logistic(X, y)
    print("coefficients fitted on all (features, then bias):")
    print("    (" + ", ".join(f"{v:.4f}" for v in w) + ")")
    for name, value in zip([*FEATURES, "bias"], w, strict=True):
        print(f"    {name:24s} {value:+.4f}")
