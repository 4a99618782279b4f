"""benchmarks/scan_sim.py's room set: furnished rooms scanned by a TLS or a rotating 2D laser,
each pair with the truth that maps its first scan onto the second, written for objects.py."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _room_modules():
    """benchmarks/_scan_sim_room.py and _scan_sim_room_scan.py as modules."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import _scan_sim_room
        import _scan_sim_room_scan
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return _scan_sim_room, _scan_sim_room_scan


def _near_share(src, tgt, T, radius):
    from scipy.spatial import cKDTree

    moved = src @ T[:3, :3].T + T[:3, 3]
    return float(np.mean(cKDTree(tgt).query(moved)[0] < radius))


@pytest.mark.parametrize("sensor", ["tls", "line2d"])
def test_a_room_pair_is_two_scans_its_truth_maps_onto_each_other(sensor):
    pytest.importorskip("open3d")
    _, scan = _room_modules()
    n = 8000 if sensor == "tls" else 60000  # the 2D laser: 55 lines
    (src, tgt, T), info = scan.room_pair(0, "furnished", sensor, points=n, distance=2.0)
    for points in (src, tgt):
        assert len(points) == pytest.approx(n, rel=0.3)
        # in the scanner's frame: a room of 4-9 m around it
        assert 3.5 < np.max(np.ptp(points, axis=0)) < 15
    assert info["size"] == max(info["room_m"][:2]) and info["voxel"] == scan.ROOM_VOXEL
    assert np.linalg.norm(T[:3, 3]) == pytest.approx(2.0, abs=0.05)  # 2 m apart, levelled
    assert abs(np.degrees(np.arcsin(np.hypot(*T[2, :2])))) < 5
    off = np.eye(4)
    off[:3, :3] = scan.rotation_xyz(0, 0, 3)
    off[:3, 3] = (0.25, 0.0, 0.0)
    # TLS rays 2 deg apart (the 2D laser's lines 3.3 deg): 7-12 cm at 2 m
    right, wrong = _near_share(src, tgt, T, 0.12), _near_share(src, tgt, off @ T, 0.12)
    assert right > 0.6 and right > wrong + 0.15, (right, wrong)
    again = scan.room_pair(0, "furnished", sensor, points=n, distance=2.0)[0]
    for a, b in zip((src, tgt, T), again, strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_2d_laser_scans_lines_and_the_tls_a_grid():
    _, scan = _room_modules()
    line = scan.scanner("line2d", 50000)
    assert line.step_deg > 4 * scan.LINE_STEP_DEG  # lines far apart, rays close along them
    tls = scan.scanner("tls", 50000)
    assert len(tls.directions) == pytest.approx(50000 / 0.9, rel=0.05)
    elevation = np.degrees(np.arcsin(tls.directions[:, 2]))
    assert elevation.min() == pytest.approx(-60) and elevation.max() > 89
    np.testing.assert_allclose(np.linalg.norm(line.directions, axis=1), 1.0)


def test_a_symmetric_room_is_its_own_turn_but_for_one_box():
    o3d = pytest.importorskip("open3d")
    room_module, scan = _room_modules()
    room = room_module.room_mesh(2, "symmetric")
    L, W, _ = room.size
    o3d.utility.random.seed(0)
    points = np.asarray(room.mesh.sample_points_uniformly(20000).points)
    turned = np.column_stack([L - points[:, 0], W - points[:, 1], points[:, 2]])
    scene = scan.raycasting_scene(room.mesh)
    off = scene.compute_distance(o3d.core.Tensor(turned.astype(np.float32))).numpy()
    assert 0.97 < np.mean(off < 0.01) < 1.0
    with pytest.raises(ValueError, match="layout 'round'"):
        room_module.room_mesh(0, "round")


def test_scan_sim_writes_the_room_pairs_and_their_list(tmp_path):
    pytest.importorskip("open3d")
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "scan_sim.py"), "--out", str(tmp_path),
         "--sets", "room", "--rooms", "r1-tls-cross-2.5m", "r4-line-1.5m",
         "--room-points", "5000"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    lines = (tmp_path / "pairs.txt").read_text().splitlines()
    assert lines == [f"{n}/source.ply {n}/target.ply out/{n}.txt"
                     for n in ("r1-tls-cross-2.5m", "r4-line-1.5m")]  # fmt: skip
    assert (tmp_path / "out").is_dir()
    cross = json.loads((tmp_path / "r1-tls-cross-2.5m" / "info.json").read_text())
    assert cross["kind"] == "room" and cross["cross_partition"] and cross["sensor"] == "tls"
    assert 0.0 < cross["overlap"] <= 1.0 and cross["points_src"] > 3000
    assert np.loadtxt(tmp_path / "r4-line-1.5m" / "T_gt.txt").shape == (4, 4)
