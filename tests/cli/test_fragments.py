"""`byoc make-fragments` end to end on a synthetic posed sequence; exit codes of bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from byoc_cli.io import read_gt_info, read_gt_log, read_gt_overlap
from tests.cli._run import invoke as _invoke
from tests.cli._run import one_error_line as _one_error_line
from tests.pipeline import _synthetic as syn

FAST = ["--frames-per-fragment", "5", "--tsdf-voxel", "0.02", "--sdf-trunc", "0.06"]


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return syn.write_sequence(tmp_path_factory.mktemp("cli") / "room", syn.orbit_poses(15))


def test_make_fragments_writes_the_benchmark(room, tmp_path):
    out = tmp_path / "bench"
    result = _invoke(["make-fragments", "--rgbd-dir", room, "--out", out, *FAST])
    assert result.exit_code == 0, result.output
    # the sequence seq-01 lies below --rgbd-dir: the scene is named after both
    scene = "room-seq-01"
    assert sorted(p.name for p in (out / scene).iterdir()) == [
        f"cloud_bin_{k}.ply" for k in range(3)
    ]
    records = read_gt_log(out / f"{scene}-evaluation" / "gt.log")
    infos = read_gt_info(out / f"{scene}-evaluation" / "gt.info")
    assert [(r.i, r.j) for r in records] == [(r.i, r.j) for r in infos] and records
    stdout = result.stdout.strip().splitlines()
    assert len(stdout) == 1 and f"3 fragments, {len(records)} pairs" in stdout[0]
    progress = [ln for ln in result.stderr.splitlines() if ln.startswith("byoc: fragment")]
    assert len(progress) == 3 and "frames 10-14" in progress[2]


def test_scene_and_stride_flags(room, tmp_path):
    out = tmp_path / "bench"
    args = ["make-fragments", "--rgbd-dir", room / "seq-01", "--out", out, "--scene", "kitchen"]
    result = _invoke(
        [*args, *FAST, "--stride", "2", "--intrinsics", room / "camera-intrinsics.txt"]
    )
    assert result.exit_code == 0, result.output
    assert len(list((out / "kitchen").glob("cloud_bin_*.ply"))) == 6  # starts 0, 2, ..., 10


def test_nonempty_out_is_refused(room, tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "x").write_text("x")
    result = _invoke(["make-fragments", "--rgbd-dir", room, "--out", out, *FAST])
    assert result.exit_code == 1
    _one_error_line(result, str(out), "not empty")
    assert result.stdout == ""


def test_sequence_without_poses_is_refused(tmp_path):
    root = syn.write_sequence(tmp_path / "unposed", syn.orbit_poses(6), with_poses=False)
    result = _invoke(["make-fragments", "--rgbd-dir", root, "--out", tmp_path / "o", *FAST])
    assert result.exit_code == 1
    _one_error_line(result, str(root), "poses")
    assert not (tmp_path / "o").exists()


def test_missing_folder_short_sequence_and_corrupt_frame(room, tmp_path):
    result = _invoke(["make-fragments", "--rgbd-dir", tmp_path / "nope", "--out", tmp_path / "o"])
    assert result.exit_code == 1
    _one_error_line(result, "nope", "does not exist")
    result = _invoke(["make-fragments", "--rgbd-dir", room, "--out", tmp_path / "o"])  # N = 50
    assert result.exit_code == 1
    _one_error_line(result, "fewer than one fragment")
    broken = syn.write_sequence(tmp_path / "broken", syn.orbit_poses(10))
    (broken / "seq-01" / "frame-000007.depth.png").write_bytes(b"garbage")
    result = _invoke(["make-fragments", "--rgbd-dir", broken, "--out", tmp_path / "o", *FAST])
    assert result.exit_code == 1
    _one_error_line(result, "frame-000007.depth.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken"]  # nothing half-written


@pytest.mark.parametrize(
    ("extra", "flag"),
    [
        (["--scene", "a/b"], "--scene"),
        (["--sdf-trunc", "0.01"], "--sdf-trunc"),
        (["--min-overlap", "1"], "--min-overlap"),
        (["--max-overlap", "0"], "--max-overlap"),
        (["--max-overlap", "1.5"], "--max-overlap"),
        (["--min-overlap", "0.3", "--max-overlap", "0.3"], "--max-overlap"),
        (["--min-overlap", "0.5", "--max-overlap", "0.2"], "--max-overlap"),
        (["--frames-per-fragment", "0"], "--frames-per-fragment"),
    ],
)
def test_usage_errors_exit_2_naming_the_flag(room, tmp_path, extra, flag):
    base = ["make-fragments", "--rgbd-dir", room, "--out", tmp_path / "o", *FAST]
    result = _invoke([*base, *extra])
    assert result.exit_code == 2 and flag in result.stderr, result.stderr
    assert not (tmp_path / "o").exists()


def test_eval_fmr_reads_the_made_benchmark(room, tmp_path):
    out = tmp_path / "bench"
    assert _invoke(["make-fragments", "--rgbd-dir", room, "--out", out, *FAST]).exit_code == 0
    result = _invoke(["eval-fmr", out, "--method", "identity", "--quiet", "--json", "-"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert (
        report["num_pairs"]
        == report["num_pairs_with_info"]
        == len(read_gt_log(out / "room-seq-01-evaluation" / "gt.log"))
    )


def _overlaps(out: Path, scene: str = "room-seq-01") -> dict[tuple[int, int], float]:
    return read_gt_overlap(out / f"{scene}-evaluation" / "gt_overlap.log")


def test_an_overlap_band_splits_gt_log_like_3dmatch_and_3dlomatch(room, tmp_path):
    """Every pair above 0, then the low band (0, x] and the high band (x, 1] with x between two
    measured overlaps: the two gt.logs split the first one exactly, each pair with its matrix."""
    every = tmp_path / "every"
    result = _invoke(
        ["make-fragments", "--rgbd-dir", room, "--out", every, *FAST, "--min-overlap", "0"]
    )
    assert result.exit_code == 0, result.output
    overlaps = _overlaps(every)
    values = sorted(overlaps.values())
    assert len(values) == 3 and values[0] < values[-1]  # 3 fragments, all overlapping
    cut = (values[0] + values[1]) / 2
    low, high = tmp_path / "low", tmp_path / "high"
    result = _invoke(
        ["make-fragments", "--rgbd-dir", room, "--out", low, *FAST, "--min-overlap", "0",
         "--max-overlap", f"{cut}"]
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert f"1 pairs with overlap in (0, {cut:g}]" in result.stdout
    result = _invoke(
        ["make-fragments", "--rgbd-dir", room, "--out", high, *FAST, "--min-overlap", f"{cut}"]
    )
    assert result.exit_code == 0, result.output
    assert f"2 pairs with overlap > {cut:g}" in result.stdout
    assert all(v <= cut for v in _overlaps(low).values())
    assert all(v > cut for v in _overlaps(high).values())
    assert _overlaps(low) | _overlaps(high) == overlaps
    every_log = {
        (r.i, r.j): r.T_tgt_src for r in read_gt_log(every / "room-seq-01-evaluation" / "gt.log")
    }
    for part in (low, high):
        for r in read_gt_log(part / "room-seq-01-evaluation" / "gt.log"):
            assert (r.T_tgt_src == every_log[(r.i, r.j)]).all()
    manifest = json.loads((low / "make-fragments.json").read_text())
    assert manifest["settings"]["max_overlap"] == pytest.approx(cut)


def test_eval_fmr_reports_the_overlap_bands_side_by_side(room, tmp_path):
    out = tmp_path / "bench"
    result = _invoke(
        ["make-fragments", "--rgbd-dir", room, "--out", out, *FAST, "--min-overlap", "0"]
    )
    assert result.exit_code == 0, result.output
    values = sorted(_overlaps(out).values())
    cut = (values[0] + values[1]) / 2
    # 10-30 %-style low band (the lowest pair) and high band (the other two)
    edges = f"{(values[0] + 0) / 2:.6f},{cut:.6f},1"
    args = ["eval-fmr", out, "--method", "identity", "--overlap-bands", edges]
    result = _invoke([*args, "--json", tmp_path / "r.json"])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert [b["num_pairs"] for b in report["bands"]] == [1, 2]
    assert report["num_pairs"] == 3 and report["num_pairs_outside_bands"] == 0
    assert report["settings"]["overlap_bands"] == [
        [float(e) for e in edges.split(",")[:2]],
        [float(e) for e in edges.split(",")[1:]],
    ]
    low_label, high_label = (b["label"] for b in report["bands"])
    assert f"identity {low_label}" in result.stderr and f"identity {high_label}" in result.stderr
    # a band above the lowest pair leaves it out (counted), the others are evaluated
    result = _invoke(["eval-fmr", out, "--method", "identity", "--overlap-bands",
                      f"{cut:.6f},1", "--json", "-", "--quiet"])  # fmt: skip
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["num_pairs"] == 2 and report["num_pairs_outside_bands"] == 1
    assert report["bands"][0]["results"]["identity"]["num_pairs"] == 2


@pytest.mark.parametrize("edges", ["0.3", "0.3,0.1", "a,b", "0.1,2"])
def test_eval_fmr_bad_overlap_bands_exit_2(room, tmp_path, edges):
    result = _invoke(["eval-fmr", tmp_path, "--method", "identity", "--overlap-bands", edges])
    assert result.exit_code == 2 and "--overlap-bands" in result.stderr, result.stderr


def test_eval_fmr_overlap_bands_need_gt_overlap_log(room, tmp_path):
    out = tmp_path / "bench"
    assert _invoke(["make-fragments", "--rgbd-dir", room, "--out", out, *FAST]).exit_code == 0
    gt_overlap = out / "room-seq-01-evaluation" / "gt_overlap.log"
    gt_overlap.unlink()
    result = _invoke(["eval-fmr", out, "--method", "identity", "--overlap-bands", "0.1,0.3,1"])
    assert result.exit_code == 1
    _one_error_line(result, str(gt_overlap.parent), "no gt_overlap.log", "--overlap-bands")
