"""benchmarks/ambiguity.py runs end to end on its synthetic pairs and scores its records."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _ambiguity(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    script = ROOT / "benchmarks" / "ambiguity.py"
    return subprocess.run(
        [sys.executable, str(script), "--out", str(tmp_path / "eval"), *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_ambiguity_refuses_the_development_sets_without_their_fragments(tmp_path):
    result = _ambiguity(tmp_path, "--sets", "dev-low", "synthetic")
    assert result.returncode == 2 and "--fragments None: no such folder" in result.stderr
    assert not (tmp_path / "eval").exists()


def test_ambiguity_cues_tell_the_slid_synthetic_pair_from_the_clean_one(tmp_path):
    result = _ambiguity(tmp_path, "--sets", "synthetic")
    assert result.returncode == 0, result.stderr
    assert "| synthetic | 2 | 2 | 2 | 0 (0) |" in result.stdout
    records = {r["name"]: r for r in json.loads((tmp_path / "eval" / "ambiguity-synthetic.json")
                                                  .read_text())}  # fmt: skip
    clean, slid = records["clean"], records["slid"]
    # both right (the true cabinet has more correspondences than the slid one) ...
    assert clean["right"] and slid["right"]
    # ... but the slid pair's correspondences and clouds support a pose 1.5 m away as well
    assert slid["seq_far_ratio"] > 0.8 and abs(slid["seq_far_voxels"] - 60) < 3
    assert slid["ref_ratio"] > 0.5 and slid["slide_voxels"] > 50
    # the ground truth explains the 150 true correspondences of each (and few of the others)
    assert all(150 <= r["truth_inliers"] < 170 for r in (clean, slid))
    assert all(r["result_inliers"] == r["truth_inliers"] for r in (clean, slid))  # both right
    assert "| synthetic | 0 | 0 |" in result.stdout  # no wrong result to count
    assert clean["seq_far_ratio"] < 0.1 and clean["ref_ratio"] < 0.1
    assert clean["slide_voxels"] < 3
    assert all(r["cue_seconds"] > 0 for r in records.values())


def test_ambiguity_table_counts_caught_wrong_and_lost_right_results(tmp_path):
    base = {"features": "byoc", "confidence": 0.9, "rotation_error_deg": 1.0,
            "translation_error_m": 1.5, "seconds": 1.0, "cue_seconds": 0.1,
            "restart_gain": -1.0, "seq_ratio": 0.0, "seq_wratio": 0.0, "seq_voxels": 0.0,
            "seq_far_ratio": 0.0, "seq_far_voxels": 0.0, "ref_ratio": 0.0,
            "ref_overlap_ratio": 0.0, "ref_voxels": 0.0, "slide_voxels": 0.0}  # fmt: skip
    records = [
        {**base, "name": "slid", "passed": True, "right": False, "seq_ratio": 0.8},
        {**base, "name": "ok", "passed": True, "right": True, "seq_ratio": 0.4,
         "translation_error_m": 0.02},
        {**base, "name": "gated", "passed": False, "right": False, "seq_ratio": 0.9},
    ]  # fmt: skip
    (tmp_path / "eval").mkdir()
    (tmp_path / "eval" / "ambiguity-kinect.json").write_text(json.dumps(records))
    result = _ambiguity(tmp_path, "--sets", "kinect", "synthetic", "--table-only")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert "| controls | 3 | 2 | 1 | 1 (1) |" in lines
    assert "| seq_ratio 0.3 | 1/1, lost 1/1 |" in lines
    assert "| seq_ratio 0.5 | 1/1, lost 0/1 |" in lines
    assert "| seq_ratio 0.9 | 0/1, lost 0/1 |" in lines
    assert any(line.strip().startswith("controls WRONG slid") for line in lines)
    assert "synthetic" not in result.stdout  # --table-only ran nothing


def test_ambiguity_needs_cut_dirs_for_the_cut_set(tmp_path):
    result = _ambiguity(tmp_path, "--sets", "cut")
    assert result.returncode == 2 and "--sets cut needs --cut-dirs" in result.stderr


@pytest.mark.slow
@pytest.mark.realdata
def test_ambiguity_scores_cut_pairs_by_their_source_points(tmp_path, shared_data):
    cut = tmp_path / "cut"
    made = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "cut_pairs.py"), "make", "--fragments",
         str(shared_data / "3dmatch" / "sample" / "3DMatch"), "--out", str(cut), "--per-pair", "1"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    result = _ambiguity(tmp_path, "--sets", "cut", "--cut-dirs", str(cut), "--limit", "1")
    assert result.returncode == 0, result.stderr
    (record,) = json.loads((tmp_path / "eval" / "ambiguity-cut-limit1.json").read_text())
    assert record["name"].startswith("cut:7-scenes-redkitchen-4-0-")
    assert isinstance(record["right"], bool) and record["seq_far_ratio"] >= 0.0
    assert 0 <= record["truth_inliers"] <= 5000  # correspondences the ground truth explains
    assert 0 <= record["result_inliers"] <= 5000  # and the result
    assert "| cut (12-32 %) | 1 |" in result.stdout
