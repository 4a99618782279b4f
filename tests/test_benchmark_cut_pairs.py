"""benchmarks/cut_pairs.py cuts real fragment pairs to low overlap and scores a summary on them."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "cut_pairs.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=600
    )


def _turned(T: np.ndarray, degrees: float) -> np.ndarray:
    a = math.radians(degrees)
    R = np.eye(4)
    R[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return T @ R


@pytest.mark.realdata
def test_cuts_reach_the_band_and_a_summary_is_scored(tmp_path, shared_data):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from byoc_cli.api import load_cloud
    from cut_pairs import overlap_of

    fragments = shared_data / "3dmatch" / "sample" / "3DMatch"
    out = tmp_path / "cut"
    run = _run("make", "--fragments", str(fragments), "--out", str(out), "--per-pair", "2")
    assert run.returncode == 0, run.stderr
    listed = (out / "pairs.txt").read_text().split("\n")[:-1]
    assert len(listed) == 6 and (out / "out").is_dir()  # 3 pairs of the sample, 2 cuts each
    folders = [out / line.split()[0].split("/")[0] for line in listed]
    whole = load_cloud(fragments / "7-scenes-redkitchen" / "cloud_bin_0.ply", scale=1.0)
    for folder in folders:
        info = json.loads((folder / "info.json").read_text())
        assert 0.07 <= info["overlap"] <= 0.33
        source = load_cloud(folder / "source.ply", scale=1.0).astype(np.float64)
        target = load_cloud(folder / "target.ply", scale=1.0).astype(np.float64)
        T_gt = np.loadtxt(folder / "T_gt.txt")
        moved = source @ T_gt[:3, :3].T + T_gt[:3, 3]
        assert overlap_of(moved, target) == pytest.approx(info["overlap"])
        if info["target_fragment"] == 0:
            assert len(target) < 0.8 * len(whole)  # cut, not the whole fragment
    # right, slid 1 m, turned 90 deg (all with exit 0), right but refused, refused with no T
    T_gt = [np.loadtxt(folder / "T_gt.txt") for folder in folders]
    slid = T_gt[1].copy()
    slid[:3, 3] += [1.0, 0.0, 0.0]
    given = [(T_gt[0], True), (slid, True), (_turned(T_gt[2], 90.0), True)]
    given += [(T_gt[3], False), (None, False)]
    summary = out / "summary.jsonl"
    lines = [
        json.dumps(
            {
                "source": f"{folder.name}/source.ply",
                "T_tgt_src": None if T is None else T.tolist(),
                "passed": passed,
                "confidence": 0.9 if passed else 0.1,
            }
        )
        for folder, (T, passed) in zip(folders, given, strict=False)
    ]
    summary.write_text("\n".join(lines) + "\n")
    run = _run("judge", str(summary), "--pairs")
    assert run.returncode == 0, run.stderr
    printed = run.stdout.splitlines()
    assert printed[-1] == (
        "pairs 5 RR 40.0 % right_exit0 1 wrong_exit0 2 (slid 1) refused 2"
    )  # RR: the right one and the right but refused one
    assert " slid exit 0 " in printed[1] and "moved 1.00 m" in printed[1]
    assert " wrong exit 0 " in printed[2] and "rot 90.0 deg" in printed[2]
    assert printed[4].endswith("no T")


def test_bad_arguments_are_one_line_and_exit_2(tmp_path):
    run = _run("make", "--fragments", str(tmp_path / "missing"), "--out", str(tmp_path / "o"))
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert str(tmp_path / "missing") in run.stderr.splitlines()[-1]
    run = _run(
        "make", "--fragments", str(tmp_path), "--out", str(tmp_path / "o"), "--band", "0.3", "0.1"
    )
    assert run.returncode == 2 and "--band" in run.stderr
    run = _run("judge", str(tmp_path / "none.jsonl"))
    assert run.returncode == 2 and "none.jsonl: no such file" in run.stderr


@pytest.mark.realdata
def test_view_cuts_leave_nothing_that_a_sensor_saw_through(tmp_path, shared_data):
    """A planar cut takes away surfaces in front of others that stay, which reads as free
    space under the truth; a cut by viewing directions takes whole rays away, and the truth
    keeps each cloud out of the other's free space (pipeline/visibility.py)."""
    import torch

    from byoc_cli.api import load_cloud
    from byoc_cli.geometry import voxelize
    from byoc_cli.pipeline.visibility import MAX_FREE_SPACE, free_space

    def kept(path: Path) -> np.ndarray:
        points = load_cloud(path, scale=1.0).astype(np.float64)
        return points[voxelize(torch.from_numpy(points), 0.025).point_index.numpy()]

    fragments = shared_data / "3dmatch" / "sample" / "3DMatch"
    shares = {}
    for kind in ("plane", "view"):
        out = tmp_path / kind
        flags = ["--view"] if kind == "view" else []
        args = ["make", "--fragments", str(fragments), "--out", str(out), "--per-pair", "3"]
        run = _run(*args, "--seed", "1", *flags)
        assert run.returncode == 0, run.stderr
        shares[kind] = []
        for line in (out / "pairs.txt").read_text().split("\n")[:-1]:
            folder = out / line.split("/")[0]
            info = json.loads((folder / "info.json").read_text())
            assert info["cut"] == kind and 0.07 <= info["overlap"] <= 0.33
            T_gt = np.loadtxt(folder / "T_gt.txt")
            note = free_space(kept(folder / "source.ply"), kept(folder / "target.ply"), T_gt, 0.025)
            shares[kind].append(note["free_space"])
    assert len(shares["view"]) == 9 and max(shares["view"]) < MAX_FREE_SPACE / 2
    assert max(shares["plane"]) > max(shares["view"])


@pytest.mark.realdata
def test_turn_gives_each_pair_a_rotation_of_the_benchmark_and_keeps_the_truth_of_the_points(
    tmp_path, shared_data
):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from byoc_cli.api import load_cloud
    from cut_pairs import benchmark_rotations

    fragments = shared_data / "3dmatch" / "sample" / "3DMatch"
    gt_dir = shared_data / "3dmatch" / "benchmarks" / "3DLoMatch"
    cut, turned = tmp_path / "cut", tmp_path / "turned"
    run = _run("make", "--fragments", str(fragments), "--out", str(cut), "--per-pair", "1")
    assert run.returncode == 0, run.stderr
    run = _run("turn", str(cut), "--out", str(turned), "--seed", "3", "--gt-dir", str(gt_dir))
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "3 pairs"
    assert (turned / "pairs.txt").read_text() == (cut / "pairs.txt").read_text()
    rotations = benchmark_rotations(gt_dir)
    assert len(rotations) == 1781
    for line in (turned / "pairs.txt").read_text().split("\n")[:-1]:
        name = line.split()[0].split("/")[0]
        old, new = np.loadtxt(cut / name / "T_gt.txt"), np.loadtxt(turned / name / "T_gt.txt")
        assert np.abs(rotations - new[:3, :3]).max(axis=(1, 2)).min() < 1e-12  # drawn from them
        assert np.array_equal(new[:3, 3], old[:3, 3])
        before = load_cloud(cut / name / "source.ply", scale=1.0).astype(np.float64)
        after = load_cloud(turned / name / "source.ply", scale=1.0).astype(np.float64)
        # the same points in the target's frame under each truth, up to gt.log's printed
        # digits (its rotations are orthonormal to about 1e-4: 0.5 mm at 5 m)
        np.testing.assert_allclose(
            after @ new[:3, :3].T + new[:3, 3], before @ old[:3, :3].T + old[:3, 3], atol=2e-3
        )
        assert np.array_equal(
            load_cloud(turned / name / "target.ply", scale=1.0),
            load_cloud(cut / name / "target.ply", scale=1.0),
        )
        info = json.loads((turned / name / "info.json").read_text())
        angle = math.degrees(math.acos(min(1.0, (np.trace(new[:3, :3]) - 1) / 2)))
        assert info["turned_deg"] == pytest.approx(angle)
    run = _run("turn", str(tmp_path / "nothing"), "--out", str(turned), "--gt-dir", str(gt_dir))
    assert run.returncode == 2 and "pairs.txt: no such file" in run.stderr.splitlines()[-1]
    run = _run("turn", str(cut), "--out", str(turned), "--gt-dir", str(tmp_path / "cut"))
    assert run.returncode == 2 and "no gt.log with a pair under it" in run.stderr
