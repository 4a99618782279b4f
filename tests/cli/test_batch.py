"""`byoc register-batch`: same T as single registers, shards, reruns, kill -9, bad pairs."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from byoc_cli.cli.main import cli
from byoc_cli.io import read_gt_log, write_ply

SCENE = "7-scenes-redkitchen"
FAST = ["--max-points", "1000", "--num-correspondences", "100"]
#: for tests of the batch's bookkeeping, which any recipe shows: no refinement, no fallback
COARSE = [*FAST, "--refine", "none", "--fallback", "none"]


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


@pytest.fixture(scope="module")
def sample(shared_data: Path) -> Path:
    return shared_data / "3dmatch" / "sample" / "3DMatch"


def _summary(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _ten_pairs(sample: Path, tmp_path: Path) -> Path:
    clouds = sorted((sample / SCENE).glob("cloud_bin_*.ply"))
    assert len(clouds) == 5
    lines = [f"{a} {b}" for a, b in itertools.combinations(clouds, 2)]
    listing = tmp_path / "pairs.txt"
    listing.write_text("# all pairs of the sample\n" + "\n".join(lines) + "\n")
    return listing


@pytest.mark.realdata
def test_batch_gives_the_transforms_of_single_registers(runner, sample, tmp_path):
    records = read_gt_log(sample / f"{SCENE}-evaluation" / "gt.log")
    listing = tmp_path / "list" / "pairs.txt"
    listing.parent.mkdir()
    lines = ["# source target (paths relative to this file)", ""]
    for rec in records:
        src = sample / SCENE / f"cloud_bin_{rec.j}.ply"  # gt.log: T maps fragment j into i
        tgt = sample / SCENE / f"cloud_bin_{rec.i}.ply"
        lines.append(
            f"{os.path.relpath(src, listing.parent)} {os.path.relpath(tgt, listing.parent)}"
        )
    listing.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    res = runner.invoke(cli, ["register-batch", str(listing), "--out-dir", str(out), "--seed", "3"])
    summary = _summary(out / "summary.jsonl")
    statuses = [s["status"] for s in summary]
    assert set(statuses) <= {"ok", "low_confidence"} and statuses.count("ok") >= 2
    # exit 3 when a pair is below --min-confidence (fragments 21 -> 7 at this seed), else 0
    assert res.exit_code == (3 if "low_confidence" in statuses else 0), res.output
    for rec, line in zip(records, summary, strict=True):
        single = tmp_path / f"single_{rec.i}_{rec.j}.txt"
        src = sample / SCENE / f"cloud_bin_{rec.j}.ply"
        tgt = sample / SCENE / f"cloud_bin_{rec.i}.ply"
        res = runner.invoke(cli, ["register", str(src), str(tgt), "-o", str(single), "--seed", "3"])
        assert res.exit_code == {"ok": 0, "low_confidence": 3}[line["status"]], res.output
        batch = out / f"cloud_bin_{rec.j}__cloud_bin_{rec.i}.txt"
        assert batch.read_bytes() == single.read_bytes()
        assert np.allclose(np.array(line["T_tgt_src"]), np.loadtxt(single))
        assert {"confidence", "num_inliers", "timings_s", "error"} <= line.keys()


@pytest.mark.realdata
def test_three_shards_give_the_outputs_of_one_run(runner, sample, tmp_path):
    listing = _ten_pairs(sample, tmp_path)
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    res = runner.invoke(cli, ["register-batch", str(listing), "--out-dir", str(whole), *COARSE])
    assert res.exit_code in (0, 3), res.output
    seen = []
    for i in (1, 2, 3):
        args = ["register-batch", str(listing), "--out-dir", str(parts), "--shard", f"{i}/3"]
        res = runner.invoke(cli, [*args, *COARSE])
        assert res.exit_code in (0, 3), res.output
        seen += [s["index"] for s in _summary(parts / f"summary.shard-{i}-of-3.jsonl")]
    assert sorted(seen) == list(range(10))  # disjoint, and together the whole list
    names = sorted(p.name for p in whole.glob("*.txt"))
    assert len(names) == 10 and names == sorted(p.name for p in parts.glob("*.txt"))
    for name in names:
        assert (whole / name).read_bytes() == (parts / name).read_bytes()


@pytest.mark.realdata
def test_pairs_side_by_side_give_the_transforms_of_one_thread(
    runner, sample, tmp_path, monkeypatch
):
    listing = _ten_pairs(sample, tmp_path)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # --threads writes it: restored after
    before = torch.get_num_threads()
    outputs = {}
    try:
        for count in ("1", "2"):
            out = tmp_path / f"threads{count}"
            args = ["--threads", count, "register-batch", str(listing), "--out-dir", str(out)]
            # no FPFH fallback: its pairs would report FPFH's voxel
            res = runner.invoke(cli, [*args, *FAST, "--fallback", "none"])
            assert res.exit_code in (0, 3), res.output
            outputs[count] = {p.name: p.read_bytes() for p in out.glob("*.txt")}
            summary = _summary(out / "summary.jsonl")
            assert [s["index"] for s in summary] == list(range(10))  # in list order
            encoded = [
                s["timings_s"][k] > 0 for s in summary for k in ("features_src", "features_tgt")
            ]
            # each fragment encoded once per voxel (and share of its points) its pairs chose,
            # also by two workers
            voxels = {
                (s[c], s["voxel_size"], s["voxel_choice"]["feature_points_kept"][k])
                for s in summary
                for k, c in enumerate(("source", "target"))
            }
            assert sum(encoded) == len(voxels)
    finally:
        torch.set_num_threads(before)
    assert len(outputs["1"]) == 10 and outputs["1"] == outputs["2"]


@pytest.mark.realdata
def test_a_killed_run_is_finished_by_a_rerun(sample, tmp_path):
    listing = _ten_pairs(sample, tmp_path)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "byoc_cli.cli.main", "-q", "register-batch", str(listing)]
    cmd += ["--out-dir", str(out), *FAST, "--fallback", "none"]
    proc = subprocess.Popen(cmd, stderr=subprocess.DEVNULL)
    summary = out / "summary.jsonl"
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline and proc.poll() is None:
        if summary.exists() and len(summary.read_text().splitlines()) >= 2:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = {p.name: p.stat().st_mtime_ns for p in out.glob("*.txt")}
    assert 2 <= len(done) < 10
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode in (0, 3), res.stderr
    after = {p.name: p.stat().st_mtime_ns for p in out.glob("*.txt")}
    assert len(after) == 10
    assert all(after[name] == mtime for name, mtime in done.items())  # not redone
    last_run = _summary(summary)[-10:]
    assert sum(s["status"] == "skipped" for s in last_run) == len(done)


def _cube(rng: np.random.Generator) -> np.ndarray:
    n = 3000
    pts = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = np.sign(pts[np.arange(n), axis])
    return pts * np.array([1.5, 1.0, 0.8])


def test_a_corrupt_cloud_fails_its_pair_only(runner, tmp_path):
    rng = np.random.default_rng(0)
    write_ply(tmp_path / "a.ply", _cube(rng))
    write_ply(tmp_path / "b.ply", _cube(rng) + 0.05)
    good = (tmp_path / "a.ply").read_bytes()
    (tmp_path / "bad.ply").write_bytes(good[: len(good) // 3])  # truncated
    (tmp_path / "pairs.txt").write_text("a.ply b.ply\nbad.ply b.ply\nb.ply a.ply ba.txt\n")
    res = runner.invoke(cli, ["register-batch", str(tmp_path / "pairs.txt"), *FAST])
    assert res.exit_code == 1
    summary = _summary(tmp_path / "summary.jsonl")
    assert [s["status"] for s in summary] == ["ok", "failed", "ok"]
    assert "bad.ply" in summary[1]["error"] and summary[1]["line"] == 2
    assert (tmp_path / "a__b.txt").is_file() and (tmp_path / "ba.txt").is_file()
    assert not (tmp_path / "bad__b.txt").exists()
    assert "line 2" in res.stderr
    # a rerun skips what exists and retries the failure only
    res = runner.invoke(cli, ["register-batch", str(tmp_path / "pairs.txt"), *FAST])
    assert res.exit_code == 1
    rerun = sorted(_summary(tmp_path / "summary.jsonl")[3:], key=lambda s: s["index"])
    assert [s["status"] for s in rerun] == ["skipped", "failed", "skipped"]


def test_below_min_confidence_exits_3_and_overwrite_redoes(runner, tmp_path):
    rng = np.random.default_rng(1)
    write_ply(tmp_path / "a.ply", _cube(rng))
    write_ply(tmp_path / "b.ply", _cube(rng))
    (tmp_path / "pairs.txt").write_text("a.ply b.ply\n")
    args = ["register-batch", str(tmp_path / "pairs.txt"), *FAST, "--min-confidence", "1"]
    res = runner.invoke(cli, args)
    assert res.exit_code == 3, res.output
    first = (tmp_path / "a__b.txt").stat().st_mtime_ns
    res = runner.invoke(cli, [*args, "--overwrite"])
    assert res.exit_code == 3
    assert (tmp_path / "a__b.txt").stat().st_mtime_ns != first
    summary = _summary(tmp_path / "summary.jsonl")
    assert [s["status"] for s in summary] == ["low_confidence"] * 2
    # below --min-confidence the FPFH fallback ran and the record says what it gave
    note = summary[-1]["fallback"]
    assert note["features"] == "fpfh" and isinstance(note["used"], bool)
    assert summary[-1]["features"] == ("fpfh" if note["used"] else "byoc")


def test_pairs_below_the_gate_are_named_and_a_rerun_that_skips_them_exits_3(runner, tmp_path):
    from byoc_cli.cli.batch_summary import NAMED_BELOW_GATE

    rng = np.random.default_rng(2)
    write_ply(tmp_path / "a.ply", _cube(rng))
    write_ply(tmp_path / "b.ply", _cube(rng) + 0.05)
    count = NAMED_BELOW_GATE + 2  # the same clouds: features computed once
    lines = [f"a.ply b.ply t{k}.txt" for k in range(count)]
    (tmp_path / "pairs.txt").write_text("\n".join(lines) + "\n")
    args = ["register-batch", str(tmp_path / "pairs.txt"), *COARSE, "--min-confidence", "1"]
    for run in ("first", "rerun"):
        res = runner.invoke(cli, args)
        assert res.exit_code == 3, (run, res.output)
        named = [ln for ln in res.stderr.splitlines() if "is below --min-confidence 1" in ln]
        assert len(named) == NAMED_BELOW_GATE, res.stderr
        pair = f"{tmp_path / 'a.ply'} -> {tmp_path / 'b.ply'}"
        assert named[0].startswith(f"byoc: line 1: {pair}: confidence ")
        assert ("recorded by an earlier run" in named[0]) == (run == "rerun")
        assert "byoc: and 2 more pairs below --min-confidence" in res.stderr
    assert f"{count} skipped (T file exists; {count} of them below" in res.stderr
    rerun = _summary(tmp_path / "summary.jsonl")[count:]
    assert [s["status"] for s in rerun] == ["skipped"] * count
    assert all(s["recorded"]["status"] == "low_confidence" for s in rerun)
    # the recorded confidences are judged against this run's gate; -q names nothing
    res = runner.invoke(cli, [*args[:-1], "0", "-q"])
    assert res.exit_code == 0, res.output
    assert res.stderr == ""  # -q: errors only (the summary file holds the result)
    res = runner.invoke(cli, [*args, "-q"])
    assert (res.exit_code, res.stderr) == (3, "")


@pytest.mark.parametrize(
    ("content", "extra", "message"),
    [
        ("a.ply\n", [], "line 1: expected 'source target [output [init]]'"),
        ("a.ply b.ply c.txt d e\n", [], "got 5 column"),
        ("# nothing\n\n", [], "holds no pair"),
        ("a.ply b.ply t.txt\nb.ply a.ply t.txt\n", [], "of line 1 and of line 2"),
        ("a.ply b.ply a.ply\n", [], "is an input of this run"),
        ("a.ply b.ply\n", ["--out-dir", "FILE"], "is not a folder"),
        (b"\xff\xfe\n", [], "not a UTF-8 text file"),
    ],
)
def test_bad_lists_get_one_line_and_nothing_written(runner, tmp_path, content, extra, message):
    rng = np.random.default_rng(0)
    write_ply(tmp_path / "a.ply", _cube(rng))
    write_ply(tmp_path / "b.ply", _cube(rng))
    listing = tmp_path / "pairs.txt"
    if isinstance(content, bytes):
        listing.write_bytes(content)
    else:
        listing.write_text(content)
    (tmp_path / "FILE").write_text("x")
    before = sorted(tmp_path.iterdir())
    extra = [str(tmp_path / "FILE") if e == "FILE" else e for e in extra]
    res = runner.invoke(cli, ["register-batch", str(listing), *extra])
    assert res.exit_code == 1, res.output
    assert message in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert sorted(tmp_path.iterdir()) == before


def test_missing_list_and_bad_shard(runner, tmp_path):
    res = runner.invoke(cli, ["register-batch", str(tmp_path / "none.txt")])
    assert res.exit_code == 1 and "none.txt" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    (tmp_path / "p.txt").write_text("a b\n")
    for bad in ("0/3", "4/3", "x"):
        res = runner.invoke(cli, ["register-batch", str(tmp_path / "p.txt"), "--shard", bad])
        assert res.exit_code == 2 and "--shard" in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.txt"]


# ------------------------------------------------------------------ the init column (issue 36)


def test_an_init_column_registers_its_pairs_from_the_pose(runner, tmp_path):
    from byoc_cli.io import format_transform

    rng = np.random.default_rng(4)
    box = rng.uniform(-1, 1, (20_000, 3))
    face = rng.integers(0, 3, len(box))
    box[np.arange(len(box)), face] = np.sign(box[np.arange(len(box)), face])
    room = box * np.array([1.5, 1.2, 1.0])
    T_gt = np.eye(4)
    T_gt[:3, 3] = [0.3, -0.2, 0.1]
    write_ply(tmp_path / "a.ply", room - T_gt[:3, 3])
    write_ply(tmp_path / "b.ply", room)
    guess = T_gt.copy()
    guess[:3, 3] += [0.1, 0.1, -0.05]
    (tmp_path / "guess.txt").write_text(format_transform(guess))
    listing = tmp_path / "pairs.txt"
    listing.write_text(
        "a.ply b.ply T_local.txt guess.txt\n"
        "a.ply b.ply T_missing.txt absent.txt\n"
        "a.ply b.ply T_global.txt\n"
    )
    res = runner.invoke(cli, ["register-batch", str(listing), *COARSE])
    summary = _summary(tmp_path / "summary.jsonl")
    assert [s["status"] for s in summary][:2] == ["ok", "failed"], res.output
    assert res.exit_code == 1  # the missing init file fails its pair, the others go on
    assert summary[0]["path"] == "local" and summary[0]["init"]["file"].endswith("guess.txt")
    assert summary[0]["init"]["correction"]["translation"] == pytest.approx(0.15, abs=0.01)
    assert np.allclose(np.loadtxt(tmp_path / "T_local.txt"), T_gt, atol=0.01)
    assert "absent.txt" in summary[1]["error"] and "absent.txt" in res.stderr
    assert summary[2]["path"] == "global" and summary[2]["init"] is None
    # a tight trust region: exit 3, the line says why
    listing.write_text("a.ply b.ply T_local.txt guess.txt\n")
    args = ["register-batch", str(listing), "--overwrite", "--max-correction", "10,0.05"]
    res = runner.invoke(cli, [*args, "--summary", str(tmp_path / "tight.jsonl")])
    assert res.exit_code == 3
    assert "from its init, beyond --max-correction 10.0 deg / 0.05" in res.stderr
    # a rerun that skips it still exits 3 (it never passes, whatever the gate)
    args = ["register-batch", str(listing), "--summary", str(tmp_path / "tight.jsonl")]
    assert runner.invoke(cli, [*args, "--min-confidence", "0"]).exit_code == 3


def test_an_init_column_that_is_an_output_or_an_extra_column_is_refused(runner, tmp_path):
    listing = tmp_path / "pairs.txt"
    listing.write_text("a.ply b.ply T.txt init.txt more\n")
    res = runner.invoke(cli, ["register-batch", str(listing)])
    assert res.exit_code == 1 and "'source target [output [init]]'" in res.stderr
    assert "an init column comes after the output column" in res.stderr
    (tmp_path / "init.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    listing.write_text("a.ply b.ply T.txt init.txt\nc.ply d.ply init.txt\n")
    res = runner.invoke(cli, ["register-batch", str(listing)])
    assert res.exit_code == 1 and "init.txt" in res.stderr  # an output over an input


@pytest.mark.slow
def test_a_smooth_pair_records_why_fpfh_registered_it(tmp_path):
    from byoc_cli.io import write_ply
    from tests._smooth import smooth_scan

    write_ply(tmp_path / "a.ply", smooth_scan(0))
    write_ply(tmp_path / "b.ply", smooth_scan(1))
    (tmp_path / "pairs.txt").write_text("a.ply b.ply\n")
    run = CliRunner().invoke(cli, ["register-batch", str(tmp_path / "pairs.txt"), "-q"])
    assert run.exit_code == 0, run.output
    record = json.loads((tmp_path / "summary.jsonl").read_text().splitlines()[0])
    assert record["features"] == "fpfh" and record["features_choice"]["first"] == "fpfh"
    assert record["status"] == "ok" and "first" in record["timings_s"]
