"""3DMatch ground truth: gt.log / gt.info / gt_overlap.log, scene discovery, prepared pairs."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from byoc_cli.errors import DatasetError, InputError
from byoc_cli.geometry.voxel import near_occupied
from byoc_cli.io import read_point_cloud
from byoc_cli.io.threedmatch import (
    discover_benchmark,
    discover_prepared_pairs,
    fragment_path,
    read_gt_info,
    read_gt_log,
    read_gt_overlap,
)

#: Pairs per scene of the official gt.log files (3DMatch: 1623 in all, 3DLoMatch: 1781).
COUNTS = {
    "3DMatch": {
        "7-scenes-redkitchen": 506,
        "sun3d-home_at-home_at_scan1_2013_jan_1": 156,
        "sun3d-home_md-home_md_scan9_2012_sep_30": 208,
        "sun3d-hotel_uc-scan3": 226,
        "sun3d-hotel_umd-maryland_hotel1": 104,
        "sun3d-hotel_umd-maryland_hotel3": 54,
        "sun3d-mit_76_studyroom-76-1studyroom2": 292,
        "sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika": 77,
    },
    "3DLoMatch": {
        "7-scenes-redkitchen": 525,
        "sun3d-home_at-home_at_scan1_2013_jan_1": 289,
        "sun3d-home_md-home_md_scan9_2012_sep_30": 230,
        "sun3d-hotel_uc-scan3": 218,
        "sun3d-hotel_umd-maryland_hotel1": 158,
        "sun3d-hotel_umd-maryland_hotel3": 49,
        "sun3d-mit_76_studyroom-76-1studyroom2": 240,
        "sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika": 72,
    },
}

T_TEXT = "1 0 0 0.5\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _record(i: int, j: int, n: int = 10, matrix: str = T_TEXT) -> str:
    return f"{i}\t{j}\t{n}\n{matrix}"


# ================================================================== real benchmark files


@pytest.mark.realdata
@pytest.mark.parametrize("suite", ["3DMatch", "3DLoMatch"])
def test_reads_every_pair_of_the_benchmark(shared_data, suite):
    scenes = discover_benchmark(shared_data / "3dmatch" / "benchmarks" / suite)
    assert [s.name for s in scenes] == sorted(COUNTS[suite])
    counts = {}
    for scene in scenes:
        records = read_gt_log(scene.gt_log)
        counts[scene.name] = len(records)
        infos = read_gt_info(scene.gt_info)
        assert [(r.i, r.j) for r in infos] == [(r.i, r.j) for r in records]
        assert all(r.info.shape == (6, 6) for r in infos)
        assert all(r.T_tgt_src.shape == (4, 4) for r in records)
        assert all(r.i < r.j < r.num_fragments for r in records)
        overlaps = read_gt_overlap(scene.gt_overlap)
        assert all((r.i, r.j) in overlaps for r in records)
    assert counts == COUNTS[suite]
    assert sum(counts.values()) == {"3DMatch": 1623, "3DLoMatch": 1781}[suite]


@pytest.mark.realdata
def test_official_registration_pairs_count(shared_data):
    """The 3DMatch toolbox scores the 1279 pairs with j - i > 1."""
    scenes = discover_benchmark(shared_data / "3dmatch" / "benchmarks" / "3DMatch")
    official = sum(1 for s in scenes for r in read_gt_log(s.gt_log) if r.j - r.i > 1)
    assert official == 1279


def _overlap(points_src: np.ndarray, points_tgt: np.ndarray, T: np.ndarray) -> float:
    moved = points_src @ T[:3, :3].T + T[:3, 3]
    near = near_occupied(torch.from_numpy(moved), torch.from_numpy(points_tgt), 0.03)
    return float(near.double().mean())


@pytest.mark.realdata
@pytest.mark.parametrize("suite", ["3DMatch", "3DLoMatch"])
def test_matrix_maps_fragment_j_into_fragment_i(shared_data, suite):
    """Moved with T, cloud_bin_j lands on cloud_bin_i; moved with inv(T) it does not."""
    root = shared_data / "3dmatch" / "sample" / suite
    (scene,) = discover_benchmark(root)
    for rec in read_gt_log(scene.gt_log):
        target = read_point_cloud(fragment_path(scene, rec.i)).points[::4]
        source = read_point_cloud(fragment_path(scene, rec.j)).points[::4]
        forward = _overlap(source, target, rec.T_tgt_src)
        backward = _overlap(source, target, np.linalg.inv(rec.T_tgt_src))
        assert forward > 0.1, (rec.i, rec.j, forward)
        assert forward > 3 * backward, (rec.i, rec.j, forward, backward)


@pytest.mark.realdata
def test_sample_layout_and_gt_dir(shared_data):
    root = shared_data / "3dmatch" / "sample" / "3DMatch"
    (scene,) = discover_benchmark(root)
    assert scene.name == "7-scenes-redkitchen"
    assert scene.gt_log == root / "7-scenes-redkitchen-evaluation" / "gt.log"
    assert scene.gt_info is None
    assert [(r.i, r.j) for r in read_gt_log(scene.gt_log)] == [(0, 4), (4, 7), (7, 21)]
    gt_dir = shared_data / "3dmatch" / "benchmarks" / "3DMatch"
    (scene,) = discover_benchmark(root, gt_dir)
    assert scene.gt_log == root / "7-scenes-redkitchen-evaluation" / "gt.log"
    assert scene.gt_info == gt_dir / "7-scenes-redkitchen" / "gt.info"


@pytest.mark.realdata
def test_sample_gt_log_agrees_with_the_benchmark(shared_data):
    sample = discover_benchmark(shared_data / "3dmatch" / "sample" / "3DLoMatch")[0]
    full = {
        (r.i, r.j): r.T_tgt_src
        for r in read_gt_log(
            shared_data / "3dmatch" / "benchmarks" / "3DLoMatch" / sample.name / "gt.log"
        )
    }
    records = read_gt_log(sample.gt_log)
    assert len(records) == 5
    for rec in records:
        np.testing.assert_allclose(rec.T_tgt_src, full[(rec.i, rec.j)], atol=1e-8)


@pytest.mark.realdata
def test_prepared_pair_folder(shared_data, tmp_path):
    demo = shared_data / "pairs" / "3dmatch_demo"
    (pair,) = discover_prepared_pairs(demo)
    assert pair.source == demo / "source.ply" and pair.target == demo / "target.ply"
    assert pair.T_gt.shape == (4, 4)
    for name in ("0001", "0000"):
        shutil.copytree(demo, tmp_path / name)
    (tmp_path / "incomplete").mkdir()
    (tmp_path / "incomplete" / "source.ply").write_bytes(b"")
    pairs = discover_prepared_pairs(tmp_path)
    assert [p.name for p in pairs] == ["0000", "0001"]


# ================================================================== parsing, synthetic


def test_parses_records_and_direction(tmp_path):
    path = _write(tmp_path / "gt.log", _record(0, 3) + "\n" + _record(2, 5, matrix=T_TEXT))
    records = read_gt_log(path)
    assert [(r.i, r.j, r.num_fragments, r.line) for r in records] == [(0, 3, 10, 1), (2, 5, 10, 7)]
    np.testing.assert_array_equal(records[0].T_tgt_src[:3, 3], [0.5, 0, 0])


@pytest.mark.parametrize(
    ("text", "line", "phrase"),
    [
        ("0 1\n" + T_TEXT, 1, "expected 3 numbers"),
        ("0 1 10\n1 0 0 0\n0 1 0 x\n0 0 1 0\n0 0 0 1\n", 3, "not a number"),
        ("0 1 10\n1 0 0 0\n0 1 0 0\n0 0 1 0\n", 1, "truncated"),
        ("0 1 10\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n", 5, "0 0 0 1"),
        ("0 1 10\n1 0 0 0\n0 1 0 0\n0 0 1 nan\n0 0 0 1\n", 4, "NaN"),
        ("0 1 10\n2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", 2, "not a rigid transform"),
        ("0 0 10\n" + T_TEXT, 1, "with itself"),
        ("0 1.5 10\n" + T_TEXT, 1, "integers"),
        ("0 12 10\n" + T_TEXT, 1, "out of range"),
        (_record(0, 1) + _record(0, 1), 6, "repeats the record of line 1"),
        ("0 1 10\n1 0 0 0 9\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", 2, "expected 4 numbers"),
    ],
)
def test_malformed_gt_log_names_file_and_line(tmp_path, text, line, phrase):
    path = _write(tmp_path / "gt.log", text)
    with pytest.raises(InputError) as info:
        read_gt_log(path)
    assert info.value.path == str(path)
    assert f"line {line}:" in info.value.problem
    assert phrase in info.value.problem


def test_missing_and_binary_gt_log(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_gt_log(tmp_path / "gt.log")
    (tmp_path / "bin.log").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(InputError, match="not a text file"):
        read_gt_log(tmp_path / "bin.log")


def test_gt_info_and_overlap(tmp_path):
    info = np.arange(36, dtype=float).reshape(6, 6)
    text = "1 4 10\n" + "\n".join(" ".join(f"{v:g}" for v in row) for row in info) + "\n"
    (record,) = read_gt_info(_write(tmp_path / "gt.info", text))
    assert (record.i, record.j) == (1, 4)
    np.testing.assert_array_equal(record.info, info)
    with pytest.raises(InputError, match="line 7"):
        read_gt_info(_write(tmp_path / "bad.info", text.rsplit("\n", 2)[0] + "\n1 2\n"))
    overlaps = read_gt_overlap(_write(tmp_path / "gt_overlap.log", "0,1,0.8\n\n2,5,0.25\n"))
    assert overlaps == {(0, 1): 0.8, (2, 5): 0.25}
    with pytest.raises(InputError, match="line 1"):
        read_gt_overlap(_write(tmp_path / "bad.log", "0,1\n"))


def test_discovery_layouts_and_errors(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        discover_benchmark(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no 3DMatch scene"):
        discover_benchmark(tmp_path / "empty")
    # official layout, gt.info from a separate ground-truth folder
    root = tmp_path / "root"
    _write(root / "scene-evaluation" / "gt.log", _record(0, 1))
    _write(root / "scene" / "cloud_bin_0.ply", "")
    gt = tmp_path / "gt"
    _write(gt / "scene" / "gt.info", "")
    (scene,) = discover_benchmark(root, gt)
    assert scene.fragment_dir == root / "scene"
    assert scene.gt_info == gt / "scene" / "gt.info"
    assert fragment_path(scene, 7) == root / "scene" / "cloud_bin_7.ply"
    # fragments without any gt.log
    _write(root / "other" / "cloud_bin_0.ply", "")
    with pytest.raises(DatasetError, match=r"no gt\.log"):
        discover_benchmark(root)
    with pytest.raises(DatasetError, match="ground-truth folder does not exist"):
        discover_benchmark(root, tmp_path / "nothing")


def test_prepared_pairs_errors(tmp_path):
    with pytest.raises(DatasetError, match="no prepared pair"):
        discover_prepared_pairs(tmp_path)
    folder = tmp_path / "0000"
    for name in ("source.ply", "target.ply"):
        _write(folder / name, "")
    _write(folder / "T_gt.txt", "1 0 0\n")
    with pytest.raises(InputError, match=r"T_gt\.txt"):
        discover_prepared_pairs(tmp_path)
