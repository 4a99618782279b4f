"""The records of a confidence collection (benchmarks/confidence.py): reading them, judging a
result right or wrong, and whether a pair's truth is determined (its two refinements agree).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from any_scan import errors  # the same judge as any_scan.py

#: a result is right within 5 deg and 10 cm (metres times the pair's scale)
ROT_DEG, TRANS_M = 5.0, 0.10
#: a wrong result that is not a near miss: beyond 15 deg or 30 cm (or no right answer)
GROSS_DEG, GROSS_M = 15.0, 0.30
#: a pair's truth is determined when its two refinements agree within these (a quarter of the
#: thresholds; metres times the pair's scale)
CHECK_DEG, CHECK_M = ROT_DEG / 4, TRANS_M / 4


def load_records(paths: list[Path]) -> list[dict]:
    """The records of the JSON-lines files ``paths``, one per pair name."""
    records = {}  # a later file's record of a pair replaces an earlier one
    for p in paths:
        for line in p.read_text().splitlines():
            if line:
                records[json.loads(line)["name"]] = json.loads(line)
    return list(records.values())


def judge(record: dict, kind: str, truth: str) -> dict | None:
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


def with_checks(records: list[dict], checked: list[Path] | None) -> list[dict]:
    """``records``, each given its second refinement (``T_gt_open3d``) from the
    `check-truth` files ``checked``, where they have one."""
    second = {r["name"]: r["T_gt_open3d"] for r in load_records(checked or [])}
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
