"""Benchmark scripts refuse bad arguments before they run anything."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

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


def _low_overlap_estimators(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    script = ROOT / "benchmarks" / "low_overlap_estimators.py"
    return subprocess.run(
        [sys.executable, str(script), "--out", str(tmp_path / "eval"), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_low_overlap_estimators_refuses_a_missing_folder_or_estimator_before_running(tmp_path):
    result = _low_overlap_estimators(tmp_path, "--fragments", str(tmp_path / "absent"))
    assert result.returncode == 2 and "no such folder" in result.stderr
    result = _low_overlap_estimators(tmp_path, "--fragments", str(tmp_path), "--estimators", "x")
    assert result.returncode == 2 and "--estimators" in result.stderr
    assert not (tmp_path / "eval").exists()


def test_low_overlap_estimators_table_scores_the_records_against_ransac(tmp_path):
    def record(j, rmse, rot, fit):
        return {"scene": "s", "i": 0, "j": j, "official": j > 1, "rmse_m": rmse,
                "rotation_error_deg": rot, "translation_error_m": 0.05, "fit_seconds": fit,
                "seconds": 2 * fit}  # fmt: skip

    (tmp_path / "eval").mkdir()
    runs = {
        "ransac": [record(2, 0.1, 1.0, 0.1), record(3, 0.5, 30.0, 0.1), record(1, 0.1, 1.0, 0.1)],
        "sc2": [record(2, 0.1, 1.0, 0.2), record(3, 0.1, 2.0, 0.2), record(1, 0.1, 1.0, 0.2)],
    }
    for name, records in runs.items():
        path = tmp_path / "eval" / f"dev-low-fpfh-{name}-coarse.json"
        path.write_text(json.dumps(records))
    args = ["--fragments", str(tmp_path), "--features", "fpfh", "--sets", "dev-low"]
    result = _low_overlap_estimators(tmp_path, *args, "--estimators", "ransac", "sc2",
                                     "--table-only")  # fmt: skip
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert (
        lines[2]
        == "| dev-low | fpfh | ransac | coarse | 50.0 (1 / 2) | 66.7 | 100.0 | 0.100 | 0.20 |"
    )
    assert lines[3].startswith("| dev-low | fpfh | sc2 | coarse | 100.0 (2 / 2) | 100.0 |")
    assert "sc2 registers 2 against RANSAC's 1 (+1 / -0 pairs), fit time x2.00" in lines[-1]


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


def _confidence(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "confidence.py"), *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT / "benchmarks",
    )


def _turned(deg: float, shift_m: float = 0.0) -> list[list[float]]:
    import numpy as np

    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[0, 3] = shift_m
    return T.tolist()


def test_fit_scores_the_determined_pairs_apart(tmp_path):
    cues = {"restart_return": 1.0, "restart_gain": -1.0, "inlier_share": 0.3,
            "inlier_ratio": 0.2, "inliers": 500.0, "overlap": 0.6, "coarse_inlier_ratio": 0.2,
            "fitness": 0.6, "rmse": 0.3, "rank": 6.0, "conditioning": 0.05, "shift_deg": 0.5,
            "shift_voxels": 0.5}  # fmt: skip
    lines, checked = [], []
    for n in range(24):
        right = n % 3 != 0
        c = {**cues, "fitness": 0.4 + 0.4 * right + 0.01 * (n % 5), "overlap": 0.3 + 0.1 * (n % 4)}
        record = {"name": f"p{n}", "group": f"g{n % 3}", "scale": 1.0,
                  "byoc": {"T": _turned(0.0), "cues": c, "confidence": 0.5},
                  "fpfh": {"skipped": "learned confidence >= 0.7"},
                  "T_gt": _turned(0.0 if right else 20.0)}  # fmt: skip
        record["T_gt_refined"] = record["T_gt"]
        lines.append(record)
        # pairs 1 and 2: the second refinement lands 6 cm or 2 deg away; 4: none
        away = {1: _turned(0.0, 0.06), 2: _turned(2.0)}.get(n, record["T_gt"])
        if n != 4:
            checked.append({"name": f"p{n}", "T_gt_open3d": away})
    dev, check = tmp_path / "dev.jsonl", tmp_path / "check.jsonl"
    dev.write_text("".join(json.dumps(line) + "\n" for line in lines))
    check.write_text("".join(json.dumps(line) + "\n" for line in checked))
    result = _confidence("fit", str(dev), "--checked", str(check))
    assert result.returncode == 0, result.stderr
    assert (
        "== pairs whose truth the data determine (its two refinements within 1.25 deg and 2.5 cm):"
        " 21 of 24; left out, by group: g1 2, g2 1" in result.stdout
    )
    assert "== learned only, determined truth only" in result.stdout
    plain = _confidence("fit", str(dev))
    assert plain.returncode == 0 and "determined truth only" not in plain.stdout


def test_the_truth_check_never_writes_over_a_file(tmp_path):
    path = tmp_path / "check.jsonl"
    path.write_text("kept\n")
    result = _confidence("check-truth", str(tmp_path / "dev.jsonl"), "--out", str(path))
    assert result.returncode == 2
    assert f"--out {path}: exists; give a new file" in result.stderr
    assert path.read_text() == "kept\n"


def test_the_second_refinement_recovers_a_box_corner_from_a_near_truth():
    import numpy as np
    import pytest

    pytest.importorskip("open3d")
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from confidence import open3d_truth
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    rng = np.random.default_rng(0)
    faces = []
    for axis in range(3):  # three walls of a 2 m corner, 1 mm noise
        p = rng.uniform(0, 2, (6000, 3))
        p[:, axis] = 0.001 * rng.standard_normal(6000)
        faces.append(p)
    tgt = np.concatenate(faces)
    T = np.array(_turned(3.0, 0.05))
    src = (tgt - T[:3, 3]) @ T[:3, :3]  # T maps src onto tgt
    near = np.array(_turned(2.0, 0.03))  # 1 deg and 2 cm from the truth
    for scale in (1.0, 0.01):
        found = open3d_truth(src * scale, tgt * scale, _scaled(near, scale), scale)
        D = np.linalg.inv(found) @ _scaled(T, scale)
        assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 0.05
        assert np.linalg.norm(D[:3, 3]) / scale < 0.002


def _scaled(T, scale: float):
    import numpy as np

    T = np.array(T, dtype=np.float64)
    T[:3, 3] *= scale
    return T


def test_agreement_counts_learned_results_against_fpfh_ones(tmp_path):
    dev, coarse = [], []
    #  name: learned result (deg), truth (deg), FPFH's unrefined result (deg or refused)
    for name, mine, truth, other in (
        ("a", 0.0, 0.0, 3.0),  # right, agrees
        ("b", 0.0, 20.0, 2.0),  # wrong, agrees
        ("c", 0.0, 0.0, 40.0),  # right, disagrees
        ("d", 0.0, 30.0, None),  # wrong, FPFH refused
    ):
        dev.append({"name": name, "group": "g", "scale": 1.0,
                    "byoc": {"T": _turned(mine), "cues": {}}, "fpfh": {"skipped": "-"},
                    "T_gt": _turned(truth), "T_gt_refined": _turned(truth)})  # fmt: skip
        fpfh = {"refused": "no"} if other is None else {"T": _turned(other), "cues": {}}
        coarse.append({"name": name, "group": "g", "scale": 1.0, "fpfh": fpfh})
    for path, lines in ((tmp_path / "dev.jsonl", dev), (tmp_path / "coarse.jsonl", coarse)):
        path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    result = _confidence(
        "agreement", str(tmp_path / "dev.jsonl"), "--coarse", str(tmp_path / "coarse.jsonl")
    )
    assert result.returncode == 0, result.stderr
    rows = {line.split()[0]: line.split()[1:] for line in result.stdout.splitlines()[2:]}
    assert rows["g"] == ["1/1", "1/0", "0/1"] and rows["all"] == rows["g"]


def _scan_sim():
    """benchmarks/scan_sim.py as a module."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import scan_sim
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return scan_sim


def test_a_simulated_street_pair_lies_on_its_scene_and_its_truth_maps_a_onto_b():
    import numpy as np

    o3d = pytest.importorskip("open3d")
    from scipy.spatial import cKDTree

    sim = _scan_sim()
    street = sim.simulate_street(2000)
    assert street.rings == 16
    for points in (street.src, street.tgt):
        assert abs(len(points) - 2000) < 200  # near what was asked
    scene = sim.raycasting_scene(street.mesh)

    def off_scene(points, T_world):
        world = sim.apply(T_world, points).astype(np.float32)
        return scene.compute_distance(o3d.core.Tensor(world)).numpy()

    # each scan in its sensor frame lies on the scene (1.5 cm range noise) ...
    for points, T_world in ((street.src, street.T_world_src), (street.tgt, street.T_world_tgt)):
        assert np.percentile(off_scene(points, T_world), 95) < 0.05
    # ... and so does A taken into B's frame by T_gt, then into the scene by B's pose
    assert np.percentile(off_scene(street.src, street.T_world_tgt @ street.T_gt), 95) < 0.05
    # A by T_gt meets B's surface, seen densely and without noise from B's sensor
    dense = sim.scan(scene, street.T_world_tgt, sim.lidar_directions(128, 4096),
                     np.random.default_rng(0), 0.0, 100.0)  # fmt: skip
    tree = cKDTree(dense)
    near = np.median(tree.query(sim.apply(street.T_gt, street.src))[0])
    off = sim.rigid(sim.rotation_xyz(0, 0, 2), (0.5, 0, 0)) @ street.T_gt
    assert near < 0.06 < 0.1 < np.median(tree.query(sim.apply(off, street.src))[0])
    # 4 m ahead, 12 deg turned: T_gt = inv(motion)
    assert np.degrees(np.arccos((np.trace(street.T_gt[:3, :3]) - 1) / 2)) == pytest.approx(12)
    assert np.linalg.norm(street.T_gt[:3, 3]) == pytest.approx(4)


def test_simulated_street_pairs_are_the_same_for_a_seed_and_sized_as_asked():
    import numpy as np

    pytest.importorskip("open3d")
    sim = _scan_sim()
    a, b = sim.street_pair(5000, seed=3), sim.street_pair(5000, seed=3)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    other = sim.street_pair(5000, seed=4)
    assert other[0].shape != a[0].shape or not np.array_equal(other[0], a[0])
    for n, rings in ((12000, 16), (40000, 32)):
        street = sim.simulate_street(n)
        assert street.rings == rings
        for points in (street.src, street.tgt):
            assert len(points) == pytest.approx(n, rel=0.05)
        assert len(sim.street_pair(n, rings=64)[0]) == pytest.approx(n, rel=0.05)


def test_georeferenced_and_scaled_pairs_keep_their_truth():
    import numpy as np

    sim = _scan_sim()
    rng = np.random.default_rng(0)
    src = rng.uniform(-50, 50, (100, 3))
    T = sim.rigid(sim.rotation_xyz(3, -2, 40), (4.0, -1.0, 0.5))
    tgt = sim.apply(T, src)
    for offset in ((1e3, 1e3, 0), (4.5e5, 5.2e6, 120), (1e7, 1e7, 0)):
        s2, t2, T2 = sim.georeferenced(src, tgt, T, offset)
        np.testing.assert_allclose(s2 - src, np.broadcast_to(offset, src.shape))
        np.testing.assert_allclose(T2[:3, :3], T[:3, :3])
        # the conjugated transform maps the moved source onto the moved target
        np.testing.assert_allclose(sim.apply(T2, s2), t2, atol=1e-9 * max(offset), rtol=0)
        np.testing.assert_allclose(T2[:3, 3], T[:3, 3] + np.asarray(offset) - T[:3, :3] @ offset)
    s3, _, T3 = sim.scaled(src, tgt, T, 1e300)
    np.testing.assert_allclose(sim.apply(T3, s3) / 1e300, tgt, atol=1e-9)


def test_scan_sim_writes_hostile_and_georeferenced_pairs_plyfile_reads(tmp_path):
    import numpy as np

    pytest.importorskip("open3d")
    from plyfile import PlyData

    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "scan_sim.py"), "--out", str(tmp_path),
         "--sets", "geo", "hostile", "--sizes", "3000"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    names = sorted(p.name for p in tmp_path.iterdir())
    assert "street-3k" not in names  # only the variants were asked for
    # float64 where float32 would lose more than a millionth of the cloud's size
    expected = {"geo-1e3": "f4", "geo-1e5": "f8", "geo-utm": "f8", "geo-1e6": "f8",
                "geo-1e7": "f8", "stray-1e6": "f8", "stray-1e30": "f8", "dup-added": "f4",
                "dup-only": "f4", "scale-1e30": "f4", "scale-1e300": "f8",
                "f32-1e9": "f4"}  # fmt: skip
    assert names == sorted(f"street-3k-{v}" for v in expected)
    for variant, dtype in expected.items():
        folder = tmp_path / f"street-3k-{variant}"
        info = json.loads((folder / "info.json").read_text())
        T = np.loadtxt(folder / "T_gt.txt")
        assert T.shape == (4, 4) and np.all(np.isfinite(T))
        for name, count in (("source.ply", info["points_src"]), ("target.ply", info["points_tgt"])):
            vertex = PlyData.read(str(folder / name))["vertex"]
            assert vertex.count == count
            assert vertex["x"].dtype == np.dtype(dtype), (variant, name)
            points = np.stack([vertex[a] for a in "xyz"], axis=1).astype(np.float64)
            assert np.all(np.isfinite(points)), variant
    dup = PlyData.read(str(tmp_path / "street-3k-dup-only" / "source.ply"))["vertex"]
    assert len(np.unique(np.stack([dup[a] for a in "xyz"], axis=1), axis=0)) == 10
    stray = PlyData.read(str(tmp_path / "street-3k-stray-1e30" / "target.ply"))["vertex"]
    far = np.stack([stray[a] for a in "xyz"], axis=1)[-1]
    assert np.linalg.norm(far) == pytest.approx(1e30)


@pytest.mark.slow  # 5-10 s: the TSDF fusion of 50 frames
@pytest.mark.realdata
def test_scan_sim_object_pair_is_two_views_of_a_small_object(shared_data, tmp_path):
    import numpy as np

    pytest.importorskip("open3d")
    from scipy.spatial import cKDTree

    sim = _scan_sim()
    sequence = shared_data / "rgbd" / "realsense_tabletop"
    src, tgt, T = sim.object_pair(45.0, spacing=1e-3, sequence=sequence, cache=tmp_path)
    assert list(tmp_path.glob("*.ply"))  # the fused mesh is cached
    assert np.degrees(np.arccos((np.trace(T[:3, :3]) - 1) / 2)) == pytest.approx(45, abs=0.5)
    for points in (src, tgt):
        assert len(points) > 5000
        assert 0.1 < np.max(np.ptp(points, axis=0)) < 0.3  # 10-30 cm across
    moved = sim.apply(T, src)
    near = cKDTree(tgt).query(moved)[0]
    assert np.mean(near < 0.002) > 0.3  # the overlap meets within 2 mm


@pytest.mark.parametrize("kind", ["blob", "superquadric", "torus", "blobs"])
def test_a_free_form_object_pair_lies_on_its_mesh_and_its_truth_maps_a_onto_b(kind):
    import numpy as np

    pytest.importorskip("open3d")
    from scipy.spatial import cKDTree

    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from _scan_sim_shapes import shape_mesh, shape_pair
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    mesh = shape_mesh(kind, 0.1, seed=3)
    extent = np.asarray(mesh.get_max_bound()) - np.asarray(mesh.get_min_bound())
    assert np.max(extent) == pytest.approx(0.1)
    src, tgt, T = shape_pair(kind, 40.0, 0.1, "handheld", resolution=150, noise=0.0, seed=3)
    for points in (src, tgt):
        assert len(points) > 3000
        assert np.max(np.ptp(points, axis=0)) < 0.25  # the object, and mixed pixels behind
    near = cKDTree(tgt).query(_scan_sim().apply(T, src))[0]
    assert np.median(near) < 0.002  # without noise the overlap meets within a ray's spacing


def test_objects_refuses_a_folder_without_a_pair_list(tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "objects.py"), "run", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "no pairs.txt" in result.stderr


def test_objects_scale_writes_the_pairs_in_other_units_and_the_truth_still_holds(tmp_path):
    import numpy as np

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from byoc_cli.io.ply import write_ply
    from objects import right

    pair = tmp_path / "src" / "blob"
    pair.mkdir(parents=True)
    rng = np.random.default_rng(0)
    src = rng.uniform(-0.05, 0.05, (200, 3)) + np.array([0.0, 0.0, 0.4])
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [0.01, 0.02, -0.03]
    write_ply(pair / "source.ply", src)
    write_ply(pair / "target.ply", src @ T[:3, :3].T + T[:3, 3])
    np.savetxt(pair / "T_gt.txt", T)
    (pair / "info.json").write_text(json.dumps({"size": 0.1, "voxel": 0.002}))
    (tmp_path / "src" / "pairs.txt").write_text("blob/source.ply blob/target.ply out/blob.txt\n")
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "objects.py"), "scale", str(tmp_path / "src"),
         "--out", str(tmp_path / "mm"), "--factor", "1000"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    mm = tmp_path / "mm" / "blob"
    info = json.loads((mm / "info.json").read_text())
    assert info["size"] == pytest.approx(100.0) and info["voxel"] == pytest.approx(2.0)
    assert (tmp_path / "mm" / "pairs.txt").read_text().startswith("blob/source.ply")
    assert (tmp_path / "mm" / "out").is_dir()
    T_mm = np.loadtxt(mm / "T_gt.txt")
    assert np.allclose(T_mm[:3, 3], 1000 * T[:3, 3])
    assert right(T_mm, mm)[0]  # the truth, in millimetres
    moved = T_mm.copy()
    moved[0, 3] += 20.0  # 2 cm: 20 % of the 10 cm object
    assert not right(moved, mm)[0]


def _scaling(*args: str, timeout: float = 120, cwd: Path | None = None):
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "scaling.py"), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
    )


def test_scaling_refuses_an_unknown_method_or_a_pair_folder_without_its_files(tmp_path):
    result = _scaling("--methods", "o3d", "magic", "--data", str(tmp_path / "pairs"))
    assert result.returncode == 2 and "--methods 'magic': not one of" in result.stderr
    result = _scaling("--sizes", "--pairs", str(tmp_path))
    assert result.returncode == 2 and f"--pairs {tmp_path}: no source.ply" in result.stderr
    assert not (tmp_path / "pairs").exists()  # nothing was generated


def _scaling_module():
    """benchmarks/scaling.py as a module."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import scaling
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return scaling


def test_scaling_fits_the_slope_over_the_sizes_that_finished():
    slopes = _scaling_module().slopes
    rows = [
        {"method": "m", "kind": "street", "points": n, "wall_s": 2.0 * n**1.5, "status": "ok"}
        for n in (1e4, 1e5, 1e6)
    ]
    rows.append({"method": "m", "kind": "street", "points": 1e7, "wall_s": 600.0,
                 "status": "timeout"})  # fmt: skip
    rows.append({"method": "n", "kind": "street", "points": 1e4, "wall_s": 1.0, "status": "ok"})
    rows.append({"method": "n", "kind": "street", "variant": "geo-1e5", "points": 1e5,
                 "wall_s": 1.0, "status": "ok"})  # fmt: skip
    fitted = slopes(rows)
    assert abs(fitted["m"] - 1.5) < 1e-9 and fitted["n"] is None


def test_scaling_measures_the_translation_error_where_the_points_are():
    import numpy as np

    scaling, sim = _scaling_module(), _scan_sim()
    T_gt = sim.rigid(sim.rotation_xyz(0, 0, 12), (4.0, 0.0, 0.0))
    T = sim.rigid(sim.rotation_xyz(0, 0, 13), (4.0, 0.0, 0.0))  # 1 deg off
    _, _, T_geo = sim.georeferenced(np.zeros((1, 3)), np.zeros((1, 3)), T, (1e6, 0, 0))
    _, _, T_gt_geo = sim.georeferenced(np.zeros((1, 3)), np.zeros((1, 3)), T_gt, (1e6, 0, 0))
    rot, at_origin = scaling.errors(T_geo, T_gt_geo)
    assert abs(rot - 1) < 1e-6 and at_origin > 1e4  # 1 deg at 1000 km
    # at the moved points, the same errors as before the move (rounding of 1e6 m aside)
    rot_at, trans_at = scaling.errors(T_geo, T_gt_geo, (1e6, 0, 0))
    assert abs(rot_at - 1) < 1e-6 and trans_at < 1e-9 and scaling.errors(T, T_gt)[1] == 0


def test_scaling_runs_open3d_on_the_smallest_street_and_prints_its_table(tmp_path):
    import numpy as np

    pytest.importorskip("open3d")
    report = tmp_path / "scaling.json"
    # a relative --data: the children run elsewhere and still find the pair
    args = ["--sizes", "10000", "--methods", "o3d", "--data", "pairs", "--timeout", "120"]
    result = _scaling(*args, "--json", str(report), timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith("| pair | points | method | wall s | CPU s | peak MB | exit |")
    cells = [c.strip() for c in lines[2].split("|")[1:-1]]
    assert cells[0] == "street-10k" and cells[2] == "o3d" and cells[6:8] == ["0", "ok"]
    assert "o3d: -" in result.stdout  # one size: no slope
    row = json.loads(report.read_text())["rows"][0]
    assert row["peak_mb"] > 0 and row["cpu_s"] > 0
    assert row["rot_deg"] < 5 and row["trans"] < 8  # Open3D at 0.3 m registers the street
    assert np.loadtxt(tmp_path / "pairs" / "street-10k" / "T_gt.txt").shape == (4, 4)


def _small_benchmark(script: str) -> list[str]:
    """The stdout lines of ``benchmarks/SCRIPT --repeat 1 --sizes N`` (N: 2000 for the k-d
    trees, 3000 for the first point per voxel), which must exit 0."""
    size = "2000" if script == "kdtree.py" else "3000"
    run = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--repeat", "1", "--sizes", size],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    return run.stdout.strip().splitlines()


def test_kdtree_times_each_tree_and_the_former_grid_on_the_same_clouds(shared_data):
    rows = _small_benchmark("kdtree.py")
    assert "pykdtree" in rows[0] and "cell grid (before)" in rows[0]
    assert [r.split()[0] for r in rows[1:]] == ["demo", "lidar", "lidar"]
    assert all(r.count(" s ") == 4 for r in rows[1:])


def test_first_per_voxel_checks_and_times_both_ways_on_the_same_clouds(shared_data):
    rows = _small_benchmark("first_per_voxel.py")
    assert rows[0].split() == ["cloud", "points", "kept", "numpy", "byoc", "ratio"]
    assert [r.split()[:2] for r in rows[1:]] == [["demo", "source"], ["ground", "3k"]]
    assert all(0 < int(r.split()[-4]) <= int(r.split()[-5]) for r in rows[1:])


def _scan_lines(*args: str) -> subprocess.CompletedProcess:
    script = ROOT / "benchmarks" / "scan_lines.py"
    return subprocess.run(
        [sys.executable, str(script), *args], capture_output=True, text=True, timeout=600
    )


def test_scan_lines_refuses_bad_arguments_before_running(tmp_path):
    taken = tmp_path / "taken.json"
    taken.write_text("{}")
    for args, message in (
        (("--seeds", "0"), "--seeds must be at least 1, got 0"),
        (("--json", str(taken)), f"--json {taken}: exists"),
    ):
        result = _scan_lines(*args)
        assert result.returncode == 2 and message in result.stderr
        assert "| rings |" not in result.stdout  # nothing ran
    assert taken.read_text() == "{}"


def test_scan_lines_registers_a_16_ring_street_with_and_without_the_measures(tmp_path):
    rows = {}
    for flag in ((), ("--without",)):
        out = tmp_path / f"runs{len(flag)}.json"
        result = _scan_lines("--pairs", "quick", "--seeds", "1", "--json", str(out), *flag)
        assert result.returncode == 0, result.stderr
        assert "| 16 | 1 | 4 m, 12 deg |" in result.stdout
        rows[flag] = json.loads(out.read_text())["pairs"][0]["runs"][0]
    with_measures, without = rows[()], rows[("--without",)]
    # the rings washed out: a coarser feature voxel, and the sensor's 4 m found
    assert with_measures["voxel"] > 3 * without["voxel"]
    assert with_measures["right"] and with_measures["translation_m"] < 0.1


def test_init_benchmark_refuses_a_collection_without_its_file_before_running(tmp_path):
    script = ROOT / "benchmarks" / "init.py"
    for args, message in ((["collect"], "collect needs --out"), (["fit"], "fit needs collections")):
        result = subprocess.run(
            [sys.executable, str(script), *args], capture_output=True, text=True, timeout=120
        )
        assert result.returncode == 2 and message in result.stderr
    result = subprocess.run(
        [sys.executable, str(script), "bench", "--pairs", "x"], capture_output=True, text=True
    )
    assert result.returncode == 2 and "--pairs" in result.stderr


def test_the_visibility_table_counts_wrong_results_above_each_threshold():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from visibility import table

    rows = [  # (set, right, passed, share, share under the truth)
        ("kinect", True, True, 0.02, 0.01),
        ("kinect", True, True, 0.05, 0.0),
        ("kinect", False, True, 0.30, 0.0),
        ("kinect", False, True, 0.07, 0.02),
        ("kinect", False, False, 0.90, 0.0),  # refused: not counted
        ("cut", True, True, 0.01, None),
    ]
    lines = table(rows, [0.06, 0.09])
    assert lines[0] == (
        "kinect: 5 results, passing 2 right / 2 wrong; largest share: right 0.050, "
        "ground truth 0.020"
    )
    assert lines[1:3] == [
        "  above 0.06: wrong 2 of 2, right lost 0",
        "  above 0.09: wrong 1 of 2, right lost 0",
    ]
    assert lines[3] == "cut: 1 results, passing 1 right / 0 wrong; largest share: right 0.010"


def test_the_visibility_benchmark_needs_something_to_measure():
    run = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "visibility.py")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 1 and "nothing to measure" in run.stderr


def test_the_visibility_frames_are_posed_pairs_of_the_shared_sequences(tmp_path, shared_data):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import numpy as np

    import visibility

    gaps = (("tum_fr1_desk", (8,)),)
    original, visibility.FRAME_GAPS = visibility.FRAME_GAPS, gaps
    try:
        made = visibility.make_frames(tmp_path)
    finally:
        visibility.FRAME_GAPS = original
    lines = (tmp_path / "pairs.txt").read_text().split("\n")[:-1]
    assert made == len(lines) >= 1 and (tmp_path / "out").is_dir()
    folder = tmp_path / lines[0].split("/")[0]
    assert folder.name.endswith("_s8")
    source = np.load(folder / "source.npy")
    T_gt = np.loadtxt(folder / "T_gt.txt")
    assert source.ndim == 2 and source.shape[1] == 3 and T_gt.shape == (4, 4)
    assert np.allclose(T_gt[:3, :3] @ T_gt[:3, :3].T, np.eye(3), atol=1e-6)
