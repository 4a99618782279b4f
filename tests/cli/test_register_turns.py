"""`byoc register --turns` and the default's turned tries (`auto`): the demo pair with its
source turned half round about its up axis (the 3DMatch fragments' vertical), as two stations
of a terrestrial scanner, or two fragments of a sweep, are."""

from __future__ import annotations

import json

import numpy as np
import pytest

from byoc_cli.api import load_cloud
from byoc_cli.geometry.orientation import turn_about, up_axis
from byoc_cli.io import write_ply
from byoc_cli.pipeline.posegraph import rotation_angle_deg
from tests.cli._run import invoke


@pytest.fixture(scope="module")
def turned_demo(shared_data, tmp_path_factory):
    """``(source turned 180 deg, target, T_gt of the turned pair)`` paths and matrix."""
    folder = shared_data / "pairs" / "3dmatch_demo"
    src = np.asarray(load_cloud(folder / "source.ply"), dtype=np.float64)
    centre = src.mean(axis=0)
    P = turn_about(up_axis(src - centre), 180.0, centre)
    out = tmp_path_factory.mktemp("turned")
    write_ply(out / "source.ply", src @ P[:3, :3].T + P[:3, 3])
    T_gt = np.loadtxt(folder / "T_gt.txt") @ np.linalg.inv(P)
    return out / "source.ply", folder / "target.ply", T_gt


def _run(paths, tmp_path, *flags):
    src, tgt, _ = paths
    report = tmp_path / "r.json"
    result = invoke(["register", src, tgt, "-o", tmp_path / "T.txt", "--json", report, *flags])
    return result, json.loads(report.read_text()), np.loadtxt(tmp_path / "T.txt")


def test_turned_learned_features_register_the_turned_pair(turned_demo, tmp_path):
    result, report, T = _run(turned_demo, tmp_path, "--turns")
    assert result.exit_code == 0, result.stderr
    D = np.linalg.inv(T) @ turned_demo[2]
    assert rotation_angle_deg(D[:3, :3]) < 5 and np.linalg.norm(D[:3, 3]) < 0.1
    turns = report["turns"]
    assert report["features"] == "byoc" and report["recipe"]["matching"]["turns"]
    assert turns["kept_deg"] in (120.0, 180.0, 240.0) and not turns["ambiguous"]
    assert len(turns["tries"]) == 6 and report["timings_s"]["turns"] > 0


def test_the_default_tries_the_turns_of_fragments_at_their_own_voxel(turned_demo, tmp_path):
    """No flags: the byoc preset's turned tries (``auto``; no structure check) register the
    turned demo pair, about the target's up axis."""
    result, report, T = _run(turned_demo, tmp_path)
    assert result.exit_code == 0, result.stderr
    D = np.linalg.inv(T) @ turned_demo[2]
    assert rotation_angle_deg(D[:3, :3]) < 5 and np.linalg.norm(D[:3, 3]) < 0.1
    turns = report["turns"]
    assert report["recipe"]["matching"]["turns"] == "auto" and turns["aligned"]
    assert turns["kept_deg"] in (120.0, 180.0, 240.0) and not turns["ambiguous"]
    assert report["confidence"] < turns["model_confidence"]  # a turned pick: discounted
    assert "structure" not in report["timings_s"]


def test_without_turns_the_learned_features_do_not_find_it(turned_demo, tmp_path):
    """The learned features alone fall below the gate on the turned pair (FPFH, the fallback,
    or nothing registers it): what --turns is for."""
    result, report, _ = _run(turned_demo, tmp_path, "--no-turns")
    assert report["turns"] is None
    assert report["features"] == "fpfh" or result.exit_code == 3


def test_turns_in_utm_coordinates_with_a_stray_point(turned_demo, tmp_path):
    """Both scans georeferenced (UTM-like offsets) and one stray return 1000 km out in the
    source: the turns run about the source's own up axis and centre, strays left out, and T
    holds in the input's coordinates (checked at the source's centroid)."""
    src_path, tgt_path, T_gt = turned_demo
    offset = np.array([4.5e5, 5.2e6, 100.0])
    src = np.asarray(load_cloud(src_path), dtype=np.float64)
    tgt = np.asarray(load_cloud(tgt_path), dtype=np.float64)
    write_ply(tmp_path / "src.ply", np.vstack([src + offset, offset + 1e6]))
    write_ply(tmp_path / "tgt.ply", tgt + offset)
    S = np.eye(4)
    S[:3, 3] = offset
    T_utm = S @ T_gt @ np.linalg.inv(S)
    paths = (tmp_path / "src.ply", tmp_path / "tgt.ply", T_utm)
    result, report, T = _run(paths, tmp_path, "--turns")
    assert result.exit_code == 0, result.stderr
    assert not report["turns"]["ambiguous"]
    centroid = src.mean(axis=0) + offset
    moved = T[:3, :3] @ centroid + T[:3, 3]
    expected = T_utm[:3, :3] @ centroid + T_utm[:3, 3]
    assert rotation_angle_deg((np.linalg.inv(T) @ T_utm)[:3, :3]) < 5
    assert np.linalg.norm(moved - expected) < 0.1
