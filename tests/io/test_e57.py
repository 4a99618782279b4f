"""E57: scans in the file's frame (their poses applied, float64), one scan at a time from a
multi-scan file, the stored poses as T_file_scan, bad files in one phrase, one-scan output."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pye57
import pytest

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io import read_point_cloud
from byoc_cli.io.e57 import (
    e57_scan_count,
    expand_scans,
    read_e57_points,
    read_e57_poses,
    write_e57,
)

#: a UTM easting, northing and height: where a georeferenced scanner export puts its scans
UTM = np.array([512345.678, 4123456.789, 123.4])
#: pye57 stores written coordinates as float32: a few metres keep about a micrometre
FLOAT32_M = 2e-6


def _rotation_z(degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _quaternion_z(degrees: float) -> np.ndarray:
    """``(w, x, y, z)`` of a turn about z (worked out by hand: cos and sin of the half angle)."""
    half = np.radians(degrees) / 2
    return np.array([np.cos(half), 0.0, 0.0, np.sin(half)])


def _local(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-5, 5, (n, 3))


def _write(path: Path, scans: list[tuple[np.ndarray, float, np.ndarray]], invalid=None) -> Path:
    """An E57 file of ``(local points, turn about z in degrees, translation)`` scans."""
    with pye57.E57(str(path), mode="w") as e57:
        for k, (local, degrees, translation) in enumerate(scans):
            data = {f"cartesian{a}": np.ascontiguousarray(local[:, j]) for j, a in enumerate("XYZ")}
            if invalid is not None and k == 0:
                data["cartesianInvalidState"] = invalid.astype(np.int8)
            e57.write_scan_raw(
                data,
                name=f"scan {k}",
                rotation=_quaternion_z(degrees),
                translation=np.asarray(translation, dtype=np.float64),
            )
    return path


@pytest.fixture
def one_scan(tmp_path) -> tuple[Path, np.ndarray]:
    local = _local(1500, 0)
    return _write(tmp_path / "one.e57", [(local, 30.0, UTM)]), local


@pytest.fixture
def two_scans(tmp_path) -> tuple[Path, list[np.ndarray]]:
    locals_ = [_local(1200, 1), _local(900, 2)]
    path = _write(
        tmp_path / "two.e57",
        [(locals_[0], 0.0, UTM), (locals_[1], -45.0, UTM + np.array([3.0, -1.0, 0.5]))],
    )
    return path, locals_


def test_a_scan_comes_in_the_files_frame_in_float64(one_scan):
    path, local = one_scan
    expected = local @ _rotation_z(30.0).T + UTM
    got = read_e57_points(path)
    assert got.dtype == np.float64
    assert np.abs(got - expected).max() < FLOAT32_M  # the pose in float64: no 0.5 m steps
    own = read_e57_points(path, apply_pose=False)
    assert np.abs(own - local).max() < FLOAT32_M
    np.testing.assert_array_equal(read_point_cloud(path).points, got)


def test_stored_poses_are_T_file_scan(two_scans):
    path, _ = two_scans
    poses = read_e57_poses(path)
    assert len(poses) == e57_scan_count(path) == 2
    expected = np.eye(4)
    expected[:3, :3], expected[:3, 3] = _rotation_z(-45.0), UTM + np.array([3.0, -1.0, 0.5])
    np.testing.assert_allclose(poses[1], expected, atol=1e-12)
    np.testing.assert_allclose(poses[0][:3, :3], np.eye(3), atol=1e-12)
    own = read_e57_points(path, 1, apply_pose=False)
    T = poses[1]
    np.testing.assert_allclose(own @ T[:3, :3].T + T[:3, 3], read_e57_points(path, 1), atol=1e-9)


def test_a_file_of_several_scans_is_read_one_scan_at_a_time(two_scans):
    path, locals_ = two_scans
    with pytest.raises(InputError) as info:
        read_point_cloud(path)
    assert info.value.problem == (
        f"holds 2 scans; give one as {path}:0 to {path}:1 (0-based), or give the file to "
        "`byoc register-scans`, which takes each scan as a cloud"
    )
    second = read_point_cloud(f"{path}:1")
    assert second.path == Path(f"{path}:1") and len(second.points) == len(locals_[1])
    assert np.abs(
        second.points - (locals_[1] @ _rotation_z(-45.0).T + UTM + np.array([3.0, -1.0, 0.5]))
    ).max() < (FLOAT32_M)
    with pytest.raises(InputError, match=r"two\.e57:2: no such scan: the file holds 2 scan\(s\)"):
        read_point_cloud(f"{path}:2")
    assert expand_scans([path, Path("x.ply"), Path(f"{path}:1")]) == [
        Path(f"{path}:0"),
        Path(f"{path}:1"),
        Path("x.ply"),
        Path(f"{path}:1"),
    ]


def test_points_flagged_invalid_are_left_out(tmp_path):
    local = _local(100, 3)
    invalid = np.zeros(100, dtype=bool)
    invalid[::4] = True
    path = _write(tmp_path / "inv.e57", [(local, 0.0, UTM)], invalid=invalid)
    got = read_e57_points(path)
    assert np.abs(got - (local[~invalid] + UTM)).max() < FLOAT32_M


@pytest.mark.parametrize(
    ("case", "phrase"),
    [
        ("garbage", "not a readable E57 file (checksum mismatch"),
        ("truncated", "not a readable E57 file (size in file header not same as actual"),
        ("empty", "not a readable E57 file"),
    ],
)
def test_a_bad_file_is_one_phrase_naming_it(one_scan, tmp_path, case, phrase):
    good, _ = one_scan
    data = {
        "garbage": b"ASTM-E57" + b"\x00" * 2000,
        "truncated": good.read_bytes()[: good.stat().st_size // 2],
        "empty": b"",
    }[case]
    path = tmp_path / "bad.e57"
    path.write_bytes(data)
    with pytest.raises(InputError) as info:
        read_point_cloud(path)
    assert info.value.path == str(path)
    assert info.value.problem.startswith(phrase), info.value.problem
    assert "\n" not in str(info.value)


def test_missing_file_and_missing_pye57(tmp_path, monkeypatch):
    with pytest.raises(InputError, match="no such file"):
        read_point_cloud(tmp_path / "none.e57")
    monkeypatch.setitem(sys.modules, "pye57", None)
    with pytest.raises(InputError, match=r"reading E57 needs pye57; install it with `pip install"):
        read_point_cloud(tmp_path / "none.e57")


def test_written_scan_reads_back_at_utm_coordinates(tmp_path):
    points = _local(3000, 4) @ _rotation_z(12.0).T + UTM
    out = tmp_path / "moved.e57"
    write_e57(out, points, name="moved")
    assert e57_scan_count(out) == 1
    back = read_e57_points(out)
    assert np.abs(back - points).max() < FLOAT32_M  # float32 about an origin in the pose
    origin = read_e57_poses(out)[0][:3, 3]
    assert np.abs(origin - UTM).max() < 6 and np.array_equal(origin, np.round(origin))
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


def test_writing_refuses_what_it_cannot_store(tmp_path):
    with pytest.raises(ShapeError):
        write_e57(tmp_path / "a.e57", np.zeros((0, 3)))
    with pytest.raises(ShapeError):
        write_e57(tmp_path / "a.e57", np.array([[np.nan, 0.0, 0.0]]))
    with pytest.raises(InputError, match="folder does not exist"):
        write_e57(tmp_path / "no" / "a.e57", np.zeros((3, 3)))
    assert not list(tmp_path.rglob("*.e57"))
