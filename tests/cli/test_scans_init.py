"""`byoc register-scans --init-poses`: known poses recovered from perturbed ones (TUM, .log,
millimetres, georeferenced), no features computed, the trust region, bad trajectories; an E57
file's stored poses as the init, and the fallback when they are wrong."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pye57
import pytest

from byoc_cli.io import read_transform, write_ply
from byoc_cli.io.trajectory import format_trajectory_log, format_tum_trajectory
from byoc_cli.pipeline import scans as scans_pipeline
from byoc_cli.pipeline.posegraph import transform_difference
from byoc_cli.pipeline.scans import ScansResult
from tests.cli._run import invoke as _invoke
from tests.cli._run import one_error_line as _one_error_line
from tests.pipeline import _rooms as rooms

UTM = np.array([512345.678, 4123456.789, 123.4])


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> list[Path]:
    folder = tmp_path_factory.mktemp("room")
    paths = [folder / f"s{k}.ply" for k in range(3)]
    for path, points in zip(paths, rooms.scans(), strict=True):
        write_ply(path, points)
    return paths


@pytest.fixture
def no_global(monkeypatch):
    """The registration without poses (features, matching) fails the test when it runs."""

    def refuse(*args, **kwargs):
        raise AssertionError("the global registration ran")

    monkeypatch.setattr(scans_pipeline, "register_scans", refuse)


def _local(T_utm: np.ndarray) -> np.ndarray:
    """A T between clouds in UTM coordinates as the T between them moved to the origin."""
    shift = rooms.turn_z(0.0, UTM)
    return np.linalg.inv(shift) @ T_utm @ shift


def _poses(out: Path, names: list[str]) -> list[np.ndarray]:
    return [read_transform(out / "poses" / f"{name}.txt") for name in names]


@pytest.mark.parametrize("fmt", ["tum", "log"])
def test_perturbed_poses_come_back_without_features(room, tmp_path, no_global, fmt):
    guesses = rooms.guesses(8.0, 0.2)
    init = tmp_path / ("init.txt" if fmt == "tum" else "init.log")
    text = format_tum_trajectory([0, 1, 2], guesses) if fmt == "tum" else None
    init.write_text(text or format_trajectory_log(guesses))
    out = tmp_path / "run"
    result = _invoke(["register-scans", *room, "--out", out, "--init-poses", init])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith(f"{out}: 3/3 scans placed, 3/3 pairs kept")
    for pose, truth in zip(_poses(out, ["s0", "s1", "s2"]), rooms.STATIONS, strict=True):
        degrees, metres = transform_difference(truth, pose)
        assert degrees < 0.1 and metres < 0.003, (degrees, metres)
    report = json.loads((out / "report.json").read_text())
    assert report["init_poses"] == {
        "source": "file",
        "path": str(init),
        "format": fmt,
        "trust_region": {"rotation_deg": 20.0, "translation": pytest.approx(1.0)},
        "used": True,
    }
    assert report["timings_s"]["features"] == 0.0
    pair = report["pairs"][0]
    assert pair["kind"] == "overlap" and pair["init"]["inside_trust_region"]
    assert pair["init"]["correction"]["rotation_deg"] == pytest.approx(8.0, abs=0.1)


def test_scans_in_millimetres_take_poses_in_millimetres(tmp_path, no_global):
    paths = [tmp_path / f"mm{k}.ply" for k in range(3)]
    for path, points in zip(paths, rooms.scans(), strict=True):
        write_ply(path, points * 1000.0)
    guesses = [g.copy() for g in rooms.guesses(8.0, 0.2)]
    for g in guesses:
        g[:3, 3] *= 1000.0
    (tmp_path / "init.txt").write_text(format_tum_trajectory([0, 1, 2], guesses))
    out = tmp_path / "run"
    args = ["register-scans", *paths, "--out", out, "--init-poses", tmp_path / "init.txt"]
    result = _invoke([*args, "--scale", "0.001", "--max-correction", "15,600"])
    assert result.exit_code == 0, result.output
    for pose, truth in zip(_poses(out, ["mm0", "mm1", "mm2"]), rooms.STATIONS, strict=True):
        in_mm = truth.copy()
        in_mm[:3, 3] *= 1000.0
        degrees, mm = transform_difference(in_mm, pose)
        assert degrees < 0.1 and mm < 3.0, (degrees, mm)
    trust = json.loads((out / "report.json").read_text())["init_poses"]["trust_region"]
    assert trust == {"rotation_deg": 15.0, "translation": pytest.approx(600.0)}


def test_georeferenced_scans_start_from_their_poses(tmp_path, no_global):
    # the scans already in one UTM frame (as a registered export), the poses a guess around
    # the identity: the result is the identity, in UTM coordinates
    paths = [tmp_path / f"g{k}.ply" for k in range(3)]
    for path, points, P in zip(paths, rooms.scans(), rooms.STATIONS, strict=True):
        write_ply(path, points @ P[:3, :3].T + P[:3, 3] + UTM)
    to_utm = rooms.turn_z(0.0, UTM)  # the trajectory's world: UTM; the truth: the identity
    guesses = rooms.guesses(6.0, 0.15, seed=3, world=np.eye(4))
    guesses = [
        to_utm @ g @ np.linalg.inv(P) @ np.linalg.inv(to_utm)
        for g, P in zip(guesses, rooms.STATIONS, strict=True)
    ]
    (tmp_path / "init.txt").write_text(format_tum_trajectory([0, 1, 2], guesses))
    out = tmp_path / "run"
    args = ["register-scans", *paths, "--out", out, "--init-poses", tmp_path / "init.txt"]
    result = _invoke(args)
    assert result.exit_code == 0, result.output
    for pose in _poses(out, ["g1", "g2"]):
        degrees, metres = transform_difference(np.eye(4), _local(pose))
        assert degrees < 0.1 and metres < 0.003, (degrees, metres)


def test_a_pair_beyond_max_correction_is_no_edge_exit_3(room, tmp_path, no_global):
    (tmp_path / "init.txt").write_text(format_tum_trajectory([0, 1, 2], rooms.guesses(8, 0.2)))
    out = tmp_path / "run"
    args = ["register-scans", *room, "--out", out, "--init-poses", tmp_path / "init.txt"]
    result = _invoke([*args, "--max-correction", "3"])
    assert result.exit_code == 3, result.output
    assert "2 scan(s) not placed" in result.stderr
    report = json.loads((out / "report.json").read_text())
    assert [p["status"] for p in report["pairs"]] == ["rejected"] * 3
    assert not any(p["init"]["inside_trust_region"] for p in report["pairs"])


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        (format_tum_trajectory([0, 1], rooms.STATIONS[:2]), "holds 2 poses for 3 scans"),
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0\n", "line 2 is not 'timestamp tx ty tz qx qy qz qw'"),
        ("# no pose\n", "holds no pose"),
    ],
)
def test_a_bad_or_short_trajectory_is_one_line_exit_1_before_any_work(room, tmp_path, text, needle):
    init = tmp_path / "init.txt"
    init.write_text(text)
    out = tmp_path / "run"
    result = _invoke(["register-scans", *room, "--out", out, "--init-poses", init])
    assert result.exit_code == 1, result.output
    _one_error_line(result, str(init), needle)
    assert not out.exists()


def test_a_missing_trajectory_and_max_correction_alone(room, tmp_path):
    out = tmp_path / "run"
    result = _invoke(["register-scans", *room, "--out", out, "--init-poses", tmp_path / "no.txt"])
    assert result.exit_code == 1
    _one_error_line(result, str(tmp_path / "no.txt"))
    result = _invoke(["register-scans", *room, "--out", out, "--max-correction", "5"])
    assert result.exit_code == 2 and "--max-correction goes with" in result.stderr
    assert not out.exists()


def _e57(path: Path, stored: list[np.ndarray]) -> Path:
    """The room's scans, each in its own frame, with ``stored`` as their poses."""
    with pye57.E57(str(path), mode="w") as e57:
        for k, (points, P) in enumerate(zip(rooms.scans(), stored, strict=True)):
            data = {f"cartesian{a}": np.ascontiguousarray(points[:, j]) for j, a in enumerate("XY")}
            data["cartesianZ"] = np.ascontiguousarray(points[:, 2])
            w = np.sqrt(max(0.0, 1 + np.trace(P[:3, :3]))) / 2  # turns about z only
            z = (P[1, 0] - P[0, 1]) / (4 * w)
            e57.write_scan_raw(
                data, name=f"scan {k}", rotation=np.array([w, 0, 0, z]), translation=P[:3, 3]
            )
    return path


def _fake_global(calls: list):
    def fake(points, *args, **kwargs):
        calls.append(len(points))
        timings = {"features": 0.0, "prepare": 0.0, "pairs": 0.0, "pose_graph": 0.0}
        return ScansResult([np.eye(4) for _ in points], [], [], timings)

    return fake


def test_an_e57_starts_from_its_stored_poses(tmp_path, no_global):
    stored = [rooms.turn_z(0.0, UTM) @ P for P in rooms.STATIONS]  # the true poses, in UTM
    site = _e57(tmp_path / "site.e57", stored)
    out = tmp_path / "run"
    result = _invoke(["register-scans", site, "--out", out])
    assert result.exit_code == 0, result.output
    assert f"{site}: starting from the scans' stored poses" in result.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["init_poses"]["source"] == "e57" and report["init_poses"]["used"]
    # the scans come in the file's frame (their poses applied): already in place there
    for pose in _poses(out, ["site_scan1", "site_scan2"]):
        degrees, metres = transform_difference(np.eye(4), _local(pose))
        assert degrees < 0.1 and metres < 0.003, (degrees, metres)


def test_wrong_stored_poses_fall_back_and_none_turns_them_off(tmp_path, monkeypatch):
    calls: list = []
    monkeypatch.setattr(scans_pipeline, "register_scans", _fake_global(calls))
    site = _e57(tmp_path / "site.e57", [rooms.turn_z(0.0, UTM)] * 3)  # one station for all
    result = _invoke(["register-scans", site, "--out", tmp_path / "a"])
    assert result.exit_code == 0, result.output
    assert calls == [3] and "registering without them" in result.stderr
    entry = json.loads((tmp_path / "a" / "report.json").read_text())["init_poses"]
    assert entry["source"] == "e57" and entry["used"] is False
    result = _invoke(["register-scans", site, "--out", tmp_path / "b", "--init-poses", "none"])
    assert result.exit_code == 0, result.output
    assert calls == [3, 3] and "stored poses" not in result.stderr
    assert json.loads((tmp_path / "b" / "report.json").read_text())["init_poses"] is None
