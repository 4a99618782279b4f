"""benchmarks/low_overlap_default.py scores a register-batch summary per band, exit code and all."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "low_overlap_default.py"


def _turned(T: np.ndarray, deg: float) -> np.ndarray:
    a = math.radians(deg)
    R = np.eye(4)
    R[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return T @ R


def test_a_summary_is_scored_per_band_with_its_exit_codes(tmp_path, shared_data):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from low_overlap_default import _pairs

    root = shared_data / "3dmatch" / "sample" / "3DLoMatch"
    gt = shared_data / "3dmatch" / "benchmarks" / "3DLoMatch"
    pairs = _pairs(root, gt)
    assert len(pairs) == 5
    # right with exit 0, wrong (turned 20 deg) with exit 0, right but refused, refused with no T
    given = [
        (pairs[0].T_gt, True),
        (_turned(pairs[1].T_gt, 20.0), True),
        (pairs[2].T_gt, False),
        (None, False),
        (_turned(pairs[4].T_gt, 90.0), False),
    ]
    lines = []
    for p, (T, passed) in zip(pairs, given, strict=True):
        lines.append(
            json.dumps(
                {
                    "source": str(p.source),
                    "target": str(p.target),
                    "status": "ok" if T is not None else "error",
                    "T_tgt_src": None if T is None else np.asarray(T).tolist(),
                    "passed": passed,
                    "confidence": 0.9 if passed else 0.1,
                }
            )
        )
    out = tmp_path / "eval"
    out.mkdir()
    (out / "summary-given.jsonl").write_text("\n".join(lines) + "\n")
    run = subprocess.run(
        [sys.executable, str(SCRIPT), "--fragments", str(root), "--gt-dir", str(gt),
         "--out", str(out), "--tag", "given"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    row = next(line for line in run.stdout.splitlines() if line.startswith("| all |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "5"
    assert cells[3:] == ["1", "1", "3", "1"]  # exit 0 right, wrong; refused; right but refused
    assert run.stderr.count("wrong, exit 0:") == 1 and " 0 34 " in run.stderr
    records = json.loads((out / "scores-given.json").read_text())
    assert [r["right"] for r in records] == [True, False, True, False, False]
    # the recall reads the transforms, exit code aside: the 20-deg turn is within 0.2 m RMSE
    # here (the count of wrong results adds the 5-deg bound), the 90-deg one is not,
    # and the pair without a transform counts as not registered
    in_rr = [p.j - p.i > 1 and p.info is not None and p.info[0][0] > 0 for p in pairs]
    assert [r["in_rr"] for r in records] == in_rr
    registered = [r["rr"] for r in records]
    assert registered == [True, True, True, False, False]
    expected = 100 * sum(x for x, k in zip(registered, in_rr, strict=True) if k) / sum(in_rr)
    assert cells[2] == f"{expected:.1f} ({sum(in_rr)})"
    assert not (out / "pairs-given.txt").exists()  # a summary there is scored, not run again


def test_a_bad_folder_or_band_list_is_one_line_and_exit_2(tmp_path):
    for extra in (["--fragments", str(tmp_path / "missing")], ["--fragments", str(tmp_path)]):
        run = subprocess.run(
            [sys.executable, str(SCRIPT), *extra, "--out", str(tmp_path / "eval")],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
        assert str(tmp_path) in run.stderr.splitlines()[-1]
    assert not (tmp_path / "eval").exists()  # nothing written
    run = subprocess.run(
        [sys.executable, str(SCRIPT), "--fragments", str(tmp_path), "--bands", "0.1,x",
         "--out", str(tmp_path / "eval")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 2 and "--bands 0.1,x" in run.stderr
