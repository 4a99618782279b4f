"""What `register` and `register-batch` say of an ambiguous result (`--turns`: another turned
try fits about as well elsewhere): one line naming it, and a rerun counts it below the gate."""

from __future__ import annotations

import json
from types import SimpleNamespace

from byoc_cli.cli.batch_summary import init_reason, recorded_below, recorded_results
from byoc_cli.cli.register import failure_line

TURNS = {
    "up_axis": [0.0, 0.0, 1.0],
    "tries": [
        {"degrees": 0.0, "confidence": 0.2, "T_tgt_src": None},
        {"degrees": 120.0, "confidence": 0.91, "T_tgt_src": None},
        {"degrees": 240.0, "confidence": 0.88, "T_tgt_src": None},
    ],
    "kept_deg": 120.0,
    "ambiguous": True,
}


def test_register_says_ambiguous_with_the_rivals_confidences():
    result = SimpleNamespace(turns=TURNS, init=None, path="global", confidence=0.91)
    line = failure_line(result, 0.45, "m")
    assert line.startswith("byoc: ambiguous: the source fits at more than one pose")
    assert "0.910 turned 120 deg, 0.880 turned 240 deg" in line and "\n" not in line


def test_a_result_that_is_not_ambiguous_is_below_the_gate_as_before():
    result = SimpleNamespace(turns={**TURNS, "ambiguous": False}, init=None, path="global")
    result.confidence = 0.3
    assert "below --min-confidence 0.45" in failure_line(result, 0.45, "m")


def test_batch_names_why_and_a_rerun_counts_it_below_the_gate(tmp_path):
    record = {"status": "low_confidence", "confidence": 0.91, "turns": TURNS, "output": "a.txt"}
    assert init_reason(record).startswith("ambiguous:")
    summary = tmp_path / "summary.jsonl"
    summary.write_text(json.dumps(record) + "\n")
    (earlier,) = recorded_results(summary).values()
    assert recorded_below(earlier, 0.45)  # its confidence alone would pass
