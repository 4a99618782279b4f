"""Benchmark scripts refuse bad arguments before they run anything."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _default_weights(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    script = ROOT / "benchmarks" / "default_weights.py"
    out = tmp_path / "eval"
    return subprocess.run(
        [sys.executable, str(script), "--out", str(out), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_default_weights_refuses_an_unknown_column_before_running(tmp_path):
    result = _default_weights(tmp_path, "--columns", "byoc", "random")
    assert result.returncode == 2
    assert "column 'random': neither byoc, byoc-random" in result.stderr
    assert "$ byoc" not in result.stderr  # no command ran
    assert not (tmp_path / "eval").exists()


def test_default_weights_refuses_a_missing_fragments_folder(tmp_path):
    result = _default_weights(tmp_path, "--fragments", str(tmp_path / "absent"))
    assert result.returncode == 2
    assert f"--fragments {tmp_path / 'absent'}: no such folder" in result.stderr
    assert not (tmp_path / "eval").exists()


def test_default_weights_takes_a_weights_file_as_a_column(tmp_path):
    weights = tmp_path / "w.safetensors"
    weights.write_bytes(b"")
    # a valid column passes the check; --table-only with no JSON runs nothing and prints "-"
    result = _default_weights(tmp_path, "--columns", str(weights), "--table-only")
    assert result.returncode == 0, result.stderr
    assert "| w.safetensors |" in result.stdout.splitlines()[0]


def _low_overlap(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    script = ROOT / "benchmarks" / "low_overlap.py"
    return subprocess.run(
        [sys.executable, str(script), "--out", str(tmp_path / "eval"), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_low_overlap_refuses_an_unknown_lever_or_a_missing_folder_before_running(tmp_path):
    result = _low_overlap(tmp_path, "--fragments", str(tmp_path), "--levers", "shipped", "magic")
    assert result.returncode == 2 and "unknown lever 'magic'" in result.stderr
    result = _low_overlap(tmp_path, "--fragments", str(tmp_path / "absent"))
    assert result.returncode == 2 and "no such folder" in result.stderr
    assert not (tmp_path / "eval").exists()


def test_low_overlap_table_only_runs_nothing(tmp_path):
    result = _low_overlap(tmp_path, "--fragments", str(tmp_path), "--levers", "mutual",
                          "--table-only")  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == "| mutual | - | - | - | - | - |"
    assert "running" not in result.stderr


def test_low_overlap_reports_of_other_weights_are_named_after_them(tmp_path):
    report = {"results": {"shipped": {"seconds_per_pair": 1.5}}}
    (tmp_path / "eval").mkdir()
    (tmp_path / "eval" / "lo-shipped-dev-low-coarse.json").write_text(json.dumps(report))
    args = ["--fragments", str(tmp_path), "--levers", "shipped", "fpfh", "--table-only"]
    result = _low_overlap(tmp_path, *args, "--coarse", "--weights", str(tmp_path / "lo.pt"))
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[-2].startswith("| lo: shipped |") and lines[-2].endswith("| 1.50 |")
    assert lines[-1] == "| fpfh | - | - | - | - | - |"  # FPFH reads no weights


def test_scans_refuses_unknown_features_or_a_missing_sequence_before_running(tmp_path):
    script = ROOT / "benchmarks" / "scans.py"
    out = tmp_path / "bench"

    def run(*args: str) -> subprocess.CompletedProcess:
        command = [sys.executable, str(script), "--out", str(out), *args]
        return subprocess.run(command, capture_output=True, text=True, timeout=60)

    result = run("--data", str(tmp_path), "--features", "fpfh")
    assert (
        result.returncode == 2 and f"--data {tmp_path}: no rgbd/tum_fr1_desk_full" in result.stderr
    )
    result = run("--features", "fpfh", "magic")
    assert result.returncode == 2 and "--features 'magic'" in result.stderr
    result = run("--fragments", str(tmp_path))
    assert (
        result.returncode == 2
        and f"--fragments {tmp_path}: no make-fragments.json" in result.stderr
    )
    assert "$ byoc" not in result.stderr and not out.exists()


def test_the_restart_floor_table_counts_what_each_floor_would_skip(tmp_path):
    lines = [
        {"name": "a", "calls": [{"model": "byoc", "before": 0.9, "after": 0.5,
                                 "restart_seconds": 1.0}]},
        {"name": "b", "calls": [{"model": "byoc", "before": 0.15, "after": 0.1,
                                 "restart_seconds": 2.0},
                                {"model": "fpfh", "before": 0.01, "after": 0.02,
                                 "restart_seconds": 0.5}]},
        {"name": "c", "refused": "noise", "calls": []},
    ]  # fmt: skip
    path = tmp_path / "floor.jsonl"
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "confidence.py"), "floor-table", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT / "benchmarks",
    )
    assert result.returncode == 0, result.stderr
    rows = {line.split()[0]: line.split() for line in result.stdout.splitlines()[2:]}
    assert "raised the confidence of 1, by at most 0.010" in result.stdout
    assert rows["0.05"][1:4] == ["1", "3", "0"]  # the FPFH one only
    assert rows["0.20"][1:4] == ["2", "3", "0"] and rows["0.20"][5] == "2.5"
    assert rows["0.45"][6] == "3.5"


def test_the_restart_floor_collection_never_writes_over_a_file(tmp_path):
    path = tmp_path / "floor.jsonl"
    path.write_text("kept\n")
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "confidence.py"), "floor", "--out", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert f"--out {path}: exists; give a new file" in result.stderr
    assert path.read_text() == "kept\n"


def _confidence(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "confidence.py"), *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT / "benchmarks",
    )


def _turned(deg: float, shift_m: float = 0.0) -> list[list[float]]:
    import numpy as np

    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[0, 3] = shift_m
    return T.tolist()


def test_fit_scores_the_determined_pairs_apart(tmp_path):
    cues = {"restart_return": 1.0, "restart_gain": -1.0, "inlier_share": 0.3,
            "inlier_ratio": 0.2, "inliers": 500.0, "overlap": 0.6, "coarse_inlier_ratio": 0.2,
            "fitness": 0.6, "rmse": 0.3, "rank": 6.0, "conditioning": 0.05, "shift_deg": 0.5,
            "shift_voxels": 0.5}  # fmt: skip
    lines, checked = [], []
    for n in range(24):
        right = n % 3 != 0
        c = {**cues, "fitness": 0.4 + 0.4 * right + 0.01 * (n % 5), "overlap": 0.3 + 0.1 * (n % 4)}
        record = {"name": f"p{n}", "group": f"g{n % 3}", "scale": 1.0,
                  "byoc": {"T": _turned(0.0), "cues": c, "confidence": 0.5},
                  "fpfh": {"skipped": "learned confidence >= 0.7"},
                  "T_gt": _turned(0.0 if right else 20.0)}  # fmt: skip
        record["T_gt_refined"] = record["T_gt"]
        lines.append(record)
        # pairs 1 and 2: the second refinement lands 6 cm or 2 deg away; 4: none
        away = {1: _turned(0.0, 0.06), 2: _turned(2.0)}.get(n, record["T_gt"])
        if n != 4:
            checked.append({"name": f"p{n}", "T_gt_open3d": away})
    dev, check = tmp_path / "dev.jsonl", tmp_path / "check.jsonl"
    dev.write_text("".join(json.dumps(line) + "\n" for line in lines))
    check.write_text("".join(json.dumps(line) + "\n" for line in checked))
    result = _confidence("fit", str(dev), "--checked", str(check))
    assert result.returncode == 0, result.stderr
    assert (
        "== pairs whose truth the data determine (its two refinements within 1.25 deg and 2.5 cm):"
        " 21 of 24; left out, by group: g1 2, g2 1" in result.stdout
    )
    assert "== learned only, determined truth only" in result.stdout
    plain = _confidence("fit", str(dev))
    assert plain.returncode == 0 and "determined truth only" not in plain.stdout


def test_the_truth_check_never_writes_over_a_file(tmp_path):
    path = tmp_path / "check.jsonl"
    path.write_text("kept\n")
    result = _confidence("check-truth", str(tmp_path / "dev.jsonl"), "--out", str(path))
    assert result.returncode == 2
    assert f"--out {path}: exists; give a new file" in result.stderr
    assert path.read_text() == "kept\n"


def test_the_second_refinement_recovers_a_box_corner_from_a_near_truth():
    import numpy as np
    import pytest

    pytest.importorskip("open3d")
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from confidence import open3d_truth
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    rng = np.random.default_rng(0)
    faces = []
    for axis in range(3):  # three walls of a 2 m corner, 1 mm noise
        p = rng.uniform(0, 2, (6000, 3))
        p[:, axis] = 0.001 * rng.standard_normal(6000)
        faces.append(p)
    tgt = np.concatenate(faces)
    T = np.array(_turned(3.0, 0.05))
    src = (tgt - T[:3, 3]) @ T[:3, :3]  # T maps src onto tgt
    near = np.array(_turned(2.0, 0.03))  # 1 deg and 2 cm from the truth
    for scale in (1.0, 0.01):
        found = open3d_truth(src * scale, tgt * scale, _scaled(near, scale), scale)
        D = np.linalg.inv(found) @ _scaled(T, scale)
        assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 0.05
        assert np.linalg.norm(D[:3, 3]) / scale < 0.002


def _scaled(T, scale: float):
    import numpy as np

    T = np.array(T, dtype=np.float64)
    T[:3, 3] *= scale
    return T


def test_agreement_counts_learned_results_against_fpfh_ones(tmp_path):
    dev, coarse = [], []
    #  name: learned result (deg), truth (deg), FPFH's unrefined result (deg or refused)
    for name, mine, truth, other in (
        ("a", 0.0, 0.0, 3.0),  # right, agrees
        ("b", 0.0, 20.0, 2.0),  # wrong, agrees
        ("c", 0.0, 0.0, 40.0),  # right, disagrees
        ("d", 0.0, 30.0, None),  # wrong, FPFH refused
    ):
        dev.append({"name": name, "group": "g", "scale": 1.0,
                    "byoc": {"T": _turned(mine), "cues": {}}, "fpfh": {"skipped": "-"},
                    "T_gt": _turned(truth), "T_gt_refined": _turned(truth)})  # fmt: skip
        fpfh = {"refused": "no"} if other is None else {"T": _turned(other), "cues": {}}
        coarse.append({"name": name, "group": "g", "scale": 1.0, "fpfh": fpfh})
    for path, lines in ((tmp_path / "dev.jsonl", dev), (tmp_path / "coarse.jsonl", coarse)):
        path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    result = _confidence(
        "agreement", str(tmp_path / "dev.jsonl"), "--coarse", str(tmp_path / "coarse.jsonl")
    )
    assert result.returncode == 0, result.stderr
    rows = {line.split()[0]: line.split()[1:] for line in result.stdout.splitlines()[2:]}
    assert rows["g"] == ["1/1", "1/0", "0/1"] and rows["all"] == rows["g"]
