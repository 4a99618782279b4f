"""gt.log / gt.info / gt_overlap.log writers: exact round trips through the readers."""

from __future__ import annotations

import numpy as np
import pytest

from byoc_cli.errors import ShapeError
from byoc_cli.io.threedmatch import read_gt_info, read_gt_log, read_gt_overlap
from byoc_cli.io.threedmatch_write import (
    format_gt_log,
    write_gt_info,
    write_gt_log,
    write_gt_overlap,
)


def _rigid(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = q, rng.normal(size=3)
    return T


def test_gt_log_round_trips_bit_for_bit(tmp_path):
    rng = np.random.default_rng(0)
    pairs = [(0, 1), (0, 3), (2, 5)]
    transforms = [_rigid(rng) for _ in pairs]
    write_gt_log(tmp_path / "gt.log", pairs, transforms, 6)
    records = read_gt_log(tmp_path / "gt.log")
    assert [(r.i, r.j, r.num_fragments) for r in records] == [(0, 1, 6), (0, 3, 6), (2, 5, 6)]
    for record, T in zip(records, transforms, strict=True):
        assert np.array_equal(record.T_tgt_src, T)
    assert [r.line for r in records] == [1, 6, 11]


def test_gt_info_and_overlap_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    pairs = [(0, 2), (1, 2)]
    infos = [(a := rng.normal(size=(6, 6))) @ a.T for _ in pairs]
    write_gt_info(tmp_path / "gt.info", pairs, infos, 3)
    records = read_gt_info(tmp_path / "gt.info")
    assert [(r.i, r.j, r.num_fragments) for r in records] == [(0, 2, 3), (1, 2, 3)]
    for record, info in zip(records, infos, strict=True):
        assert np.array_equal(record.info, info)
    write_gt_overlap(tmp_path / "gt_overlap.log", pairs, [0.5, 0.31234])
    assert read_gt_overlap(tmp_path / "gt_overlap.log") == {(0, 2): 0.5, (1, 2): 0.3123}


def test_no_pair_writes_empty_files_the_reader_accepts(tmp_path):
    write_gt_log(tmp_path / "gt.log", [], [], 1)
    write_gt_info(tmp_path / "gt.info", [], [], 1)
    assert read_gt_log(tmp_path / "gt.log") == [] and read_gt_info(tmp_path / "gt.info") == []


@pytest.mark.parametrize(
    ("pairs", "matrices", "n", "match"),
    [
        ([(1, 1)], [np.eye(4)], 3, "itself"),
        ([(0, 3)], [np.eye(4)], 3, "out of range"),
        ([(0, 1), (0, 1)], [np.eye(4)] * 2, 3, "twice"),
        ([(0, 1)], [np.eye(4), np.eye(4)], 3, "2 matrices"),
        ([(0, 1)], [np.eye(3)], 3, r"\(4, 4\)"),
        ([(0, 1)], [np.full((4, 4), np.nan)], 3, "NaN"),
        ([(0, 1)], [np.diag([2.0, 1.0, 1.0, 1.0])], 3, "rigid"),
        ([(0, 1)], [np.diag([-1.0, 1.0, 1.0, 1.0])], 3, "rigid"),
    ],
)
def test_invalid_gt_log_records_are_refused_and_nothing_is_written(
    tmp_path, pairs, matrices, n, match
):
    with pytest.raises(ShapeError, match=match):
        write_gt_log(tmp_path / "gt.log", pairs, matrices, n)
    assert not any(tmp_path.iterdir())


def test_invalid_info_and_overlap_are_refused(tmp_path):
    with pytest.raises(ShapeError, match=r"\(6, 6\)"):
        write_gt_info(tmp_path / "gt.info", [(0, 1)], [np.eye(4)], 2)
    with pytest.raises(ShapeError, match=r"\[0, 1\]"):
        write_gt_overlap(tmp_path / "gt_overlap.log", [(0, 1)], [1.5])
    assert not any(tmp_path.iterdir())


def test_record_text_is_the_official_shape():
    text = format_gt_log([(0, 4)], [np.eye(4)], 60)
    lines = text.splitlines()
    assert lines[0].split() == ["0", "4", "60"] and len(lines) == 5
    assert all(len(line.split()) == 4 for line in lines[1:])
