"""`confidence.py fit` and `agreement`: the probability that a result is right, fitted on the
collections' cues by sequence-grouped cross-validation, its precision and recall at each
threshold and its reliability; the learned results against FPFH's unrefined ones.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from _confidence_records import CHECK_DEG, CHECK_M, determined, judge, load_records, with_checks
from any_scan import errors

#: the share of right results the default threshold keeps
RECALL = 0.95
#: a learned result agrees with FPFH's when they are this close (metres times the pair's scale)
AGREE_DEG, AGREE_M = 10.0, 0.30
KINDS = ("byoc", "fpfh")


def _cross_validated(records: list[dict], kind: str, truth: str):
    """Out-of-group probabilities of ``kind``'s results (nan where refused), the labels and
    the coefficients fitted on all."""
    from byoc_cli.pipeline.confidence import cue_matrix, fit_logistic, sigmoid

    judged = [judge(r, kind, truth) for r in records]
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

    records = with_checks(load_records(paths), checked)
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
    records = with_checks(load_records(paths), checked)
    fpfh = {r["name"]: r["fpfh"] for r in load_records(coarse)}
    counts: dict[str, Counter] = {}
    for r in records:
        judged = judge(r, "byoc", "refined")
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
