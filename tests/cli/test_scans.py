"""`byoc register-scans` end to end on fragments of a real posed sequence; bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from byoc_cli.io import read_point_cloud, read_transform, write_ply
from tests.cli._run import invoke as _invoke
from tests.cli._run import one_error_line as _one_error_line
from tests.pipeline._scans_data import desk_fragments, pose_errors


@pytest.fixture(scope="module")
def desk(shared_data, tmp_path_factory):
    clouds, gt = desk_fragments(shared_data)
    folder = tmp_path_factory.mktemp("scans")
    paths = []
    for k, cloud in enumerate(clouds):
        paths.append(folder / f"frag{k}.ply")
        write_ply(paths[-1], cloud)
    return paths, gt


@pytest.fixture(scope="module")
def run(desk, tmp_path_factory):
    paths, _ = desk
    out = tmp_path_factory.mktemp("run") / "scan"
    merged = out.parent / "merged.ply"
    result = _invoke(
        ["register-scans", *paths, "--out", out, "--features", "fpfh", "--merged", merged]
    )
    return result, out, merged


def test_register_scans_writes_poses_trajectory_report_and_model(desk, run):
    o3d = pytest.importorskip("open3d")
    paths, gt = desk
    result, out, merged = run
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith(f"{out}: 3/3 scans placed, 3/3 pairs kept")
    poses = [read_transform(out / "poses" / f"frag{k}.txt") for k in range(3)]
    rotation, translation = pose_errors(poses, gt)
    print(f"register-scans CLI: median error {rotation:.2f} deg, {100 * translation:.1f} cm")
    assert rotation < 5.0 and translation < 0.08  # measured 3.14 deg, 4.9 cm
    trajectory = o3d.io.read_pinhole_camera_trajectory(str(out / "trajectory.log"))
    got = [np.linalg.inv(p.extrinsic) for p in trajectory.parameters]
    np.testing.assert_allclose(got, poses, atol=1e-7)
    report = json.loads((out / "report.json").read_text())
    assert report["pairs_tried"] == 3 and report["pairs_kept"] == 3
    assert report["edges_pruned"] == 0 and report["unplaced"] == []
    assert all(0.3 <= p["fitness"] <= 1 for p in report["pairs"])
    assert {"load", "features", "pairs", "pose_graph", "merge"} <= set(report["timings_s"])
    model = read_point_cloud(merged).points
    # the merged model is voxelised at 1 cm: fewer points than the three fragments
    assert 0 < len(model) < sum(len(read_point_cloud(p).points) for p in paths)


def test_a_rerun_into_its_own_folder_is_allowed(desk, run, tmp_path):
    paths, _ = desk
    _, out, _ = run
    result = _invoke(["register-scans", *paths[:2], "--out", out, "--features", "fpfh"])
    assert result.exit_code == 0, result.output


def test_a_scan_that_overlaps_nothing_is_unplaced_exit_3(desk, tmp_path):
    paths, _ = desk
    rng = np.random.default_rng(0)
    elsewhere = tmp_path / "elsewhere.ply"
    ball = rng.normal(size=(5000, 3))  # a sphere's surface far away (noise is refused)
    write_ply(elsewhere, 0.5 * ball / np.linalg.norm(ball, axis=1, keepdims=True) + 50.0)
    out = tmp_path / "scan"
    result = _invoke(["register-scans", paths[0], paths[1], elsewhere, "--out", out,
                      "--features", "fpfh"])  # fmt: skip
    assert result.exit_code == 3, result.output
    assert "1 scan(s) not placed: " in result.stderr and "elsewhere.ply" in result.stderr
    assert sorted(p.name for p in (out / "poses").iterdir()) == ["frag0.txt", "frag1.txt"]
    report = json.loads((out / "report.json").read_text())
    assert report["unplaced"] == [str(elsewhere)] and report["num_placed"] == 2


# ------------------------------------------------------------------ bad input


def _cube(path: Path) -> Path:
    grid = np.stack(np.meshgrid(*[np.linspace(0, 1, 12)] * 3), -1).reshape(-1, 3)
    write_ply(path, grid)
    return path


@pytest.mark.parametrize(
    "case, needle",
    [("missing", "missing.ply"), ("corrupt", "bad.ply"), ("millimetres", "big.ply")],
)
def test_bad_scans_give_one_line_exit_1_and_no_folder(tmp_path, case, needle):
    good = _cube(tmp_path / "good.ply")
    if case == "missing":
        bad = tmp_path / "missing.ply"
    elif case == "corrupt":
        bad = tmp_path / "bad.ply"
        bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n")
    else:  # a scan in millimetres beside one in metres (both surfaces: a wavy sheet)
        good = tmp_path / "sheet.ply"
        u, v = np.meshgrid(np.linspace(0, 1, 30), np.linspace(0, 1, 30))
        sheet = np.column_stack([u.ravel(), v.ravel(), 0.1 * np.sin(6 * u.ravel())])
        write_ply(good, sheet)
        bad = tmp_path / "big.ply"
        write_ply(bad, 5000 * sheet)
    out = tmp_path / "out"
    merged = tmp_path / "merged.ply"
    result = _invoke(["register-scans", good, bad, "--out", out, "--features", "fpfh",
                      "--merged", merged])  # fmt: skip
    assert result.exit_code == 1, result.output
    _one_error_line(result, needle)
    assert not out.exists() and not merged.exists()


def test_an_existing_folder_keeps_what_it_had(tmp_path):
    good = _cube(tmp_path / "good.ply")
    out = tmp_path / "out"
    (out / "poses").mkdir(parents=True)
    result = _invoke(["register-scans", good, tmp_path / "nope.ply", "--out", out,
                      "--features", "fpfh"])  # fmt: skip
    assert result.exit_code == 1
    assert (out / "poses").is_dir() and not any((out / "poses").iterdir())


def test_a_foreign_folder_is_refused(tmp_path):
    good = _cube(tmp_path / "good.ply")
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    result = _invoke(["register-scans", good, good.with_name("x.ply"), "--out", out])
    assert result.exit_code == 1
    _one_error_line(result, "not empty")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_usage_errors_exit_2(tmp_path, monkeypatch):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a, b = _cube(tmp_path / "a" / "scan.ply"), _cube(tmp_path / "b" / "scan.ply")
    out = tmp_path / "out"
    one = _invoke(["register-scans", a, "--out", out, "--features", "fpfh"])
    assert one.exit_code == 2 and "at least 2 scans" in one.output
    same = _invoke(["register-scans", a, b, "--out", out, "--features", "fpfh"])
    assert same.exit_code == 2 and "same name" in same.output
    # an install without shipped weights: byoc features need --weights
    from byoc_cli.pipeline import default_weights

    monkeypatch.setattr(default_weights, "DEFAULT_WEIGHTS", tmp_path / "none.safetensors")
    weights = _invoke(["register-scans", a, tmp_path / "c.ply", "--out", out])
    assert weights.exit_code == 2 and "--weights" in weights.output
    assert not out.exists()


def test_scans_in_millimetres_are_brought_to_the_features_scale(desk, run, tmp_path):
    """No flags: scans 1000 times larger are registered at the features' own scale and the
    poses come back in millimetres, as accurate as the metre scans' (the test above)."""
    paths, gt = desk
    _, out_metres, _ = run
    scaled = []
    for k, path in enumerate(paths):
        scaled.append(tmp_path / f"mm{k}.ply")
        write_ply(scaled[-1], read_point_cloud(path).points * 1000.0)
    out = tmp_path / "mm"
    result = _invoke(["register-scans", *scaled, "--out", out, "--features", "fpfh"])
    assert result.exit_code == 0, result.output
    assert "3/3 scans placed" in result.stdout
    poses = [read_transform(out / "poses" / f"mm{k}.txt") for k in range(3)]
    metres = [p.copy() for p in poses]
    for p in metres:
        p[:3, 3] /= 1000.0
    rotation, translation = pose_errors(metres, gt)
    assert rotation < 5.0 and translation < 0.08
    settings = json.loads((out / "report.json").read_text())["settings"]
    assert 0.0005 < settings["scale"] < 0.005  # millimetres brought to about metres
    assert "above the trained range" in settings["voxel_choice"]["reason"]
    before = json.loads((out_metres / "report.json").read_text())["settings"]
    assert before["scale"] is None  # scans of the trained size are not rescaled
    # the pairs' T_i_j are in the input's millimetres too: they agree with the poses
    for pair in json.loads((out / "report.json").read_text())["pairs"]:
        if pair["T_i_j"] is not None and pair["edge"] and not pair["pruned"]:
            graph = np.linalg.inv(poses[pair["i"]]) @ poses[pair["j"]]
            shift = np.linalg.norm(np.array(pair["T_i_j"])[:3, 3] - graph[:3, 3])
            assert shift < 80.0, pair  # millimetres (a translation in metres would be ~1000x off)
