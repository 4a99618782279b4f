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
