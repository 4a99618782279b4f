"""`byoc register` end to end: outputs, exit codes, messages, atomicity, determinism."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli
from byoc_cli.geometry.transforms import axis_angle_to_matrix
from byoc_cli.io import read_transform, write_ply
from tests._smooth import smooth_scan


def _rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    c = (np.trace(R_a @ R_b.T) - 1) / 2
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


@pytest.fixture(scope="module")
def demo(shared_data: Path) -> Path:
    return shared_data / "pairs" / "3dmatch_demo"


@pytest.fixture(scope="module")
def random_weights(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("w") / "random.safetensors"
    result = CliRunner().invoke(cli, ["weights", "init", "--seed", "1", "-o", str(path)])
    assert result.exit_code == 0, result.output
    return path


def _synthetic_pair(tmp_path: Path) -> tuple[Path, Path, np.ndarray]:
    """A box-room-like surface and a rigidly moved copy; returns paths and T_tgt_src."""
    import torch

    rng = np.random.default_rng(0)
    n = 4000
    pts = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = np.sign(pts[np.arange(n), axis])  # points on a cube's faces
    pts = pts * np.array([1.5, 1.0, 0.8])
    R = axis_angle_to_matrix(torch.tensor([0.1, -0.2, 0.15], dtype=torch.float64)).numpy()
    t = np.array([0.2, -0.1, 0.05])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    src = tmp_path / "src.ply"
    tgt = tmp_path / "tgt.ply"
    write_ply(src, pts)
    write_ply(tgt, pts @ R.T + t)
    return src, tgt, T


@pytest.mark.realdata
def test_fpfh_registers_demo_pair(runner, demo, tmp_path):
    out = tmp_path / "T.txt"
    report = tmp_path / "r.json"
    aligned = tmp_path / "aligned.ply"
    result = runner.invoke(
        cli,
        [
            "register",
            str(demo / "source.ply"),
            str(demo / "target.ply"),
            "--features",
            "fpfh",
            "-o",
            str(out),
            "--json",
            str(report),
            "--aligned",
            str(aligned),
        ],
    )
    assert result.exit_code == 0, result.output
    T = read_transform(out)
    T_gt = np.loadtxt(demo / "T_gt.txt")
    assert _rotation_error_deg(T[:3, :3], T_gt[:3, :3]) < 5.0
    assert np.linalg.norm(T[:3, 3] - T_gt[:3, 3]) < 0.10
    data = json.loads(report.read_text())
    for key in (
        "T_tgt_src",
        "num_correspondences",
        "num_inliers",
        "inlier_ratio",
        "overlap",
        "confidence",
        "voxel_size",
        "inlier_threshold",
        "unit",
        "seed",
        "timings_s",
        "weights_sha256",
        "byoc_cli_version",
    ):
        assert key in data
    assert 0.0 <= data["confidence"] <= 1.0
    assert np.allclose(np.array(data["T_tgt_src"]), T)
    assert aligned.stat().st_size > 0


def test_same_seed_byte_identical_and_stdout(runner, random_weights, tmp_path):
    src, tgt, _ = _synthetic_pair(tmp_path)
    outs = []
    for name in ("a.txt", "b.txt"):
        path = tmp_path / name
        res = runner.invoke(
            cli,
            [
                "register",
                str(src),
                str(tgt),
                "--weights",
                str(random_weights),
                "--seed",
                "7",
                "-o",
                str(path),
            ],
        )
        assert res.exit_code == 0, res.output
        outs.append(path.read_bytes())
    assert outs[0] == outs[1]
    res = runner.invoke(
        cli,
        [
            "register",
            str(src),
            str(tgt),
            "--weights",
            str(random_weights),
            "--seed",
            "7",
            "-o",
            "-",
        ],
    )
    assert res.exit_code == 0
    assert res.stdout.encode() == outs[0]  # stdout carries the matrix only
    assert len(res.stdout.strip().splitlines()) == 4


def test_ransac_estimator_and_multiscale_recover_synthetic(runner, tmp_path):
    src, tgt, T_gt = _synthetic_pair(tmp_path)
    out = tmp_path / "T.txt"
    res = runner.invoke(
        cli,
        [
            "register",
            str(src),
            str(tgt),
            "--features",
            "fpfh",
            "--voxel-size",
            "0.05",
            "--estimator",
            "ransac",
            "--refine",
            "multiscale",
            "-o",
            str(out),
        ],
    )
    assert res.exit_code == 0, res.output
    T = read_transform(out)
    assert _rotation_error_deg(T[:3, :3], T_gt[:3, :3]) < 2.0
    assert np.linalg.norm(T[:3, 3] - T_gt[:3, 3]) < 0.05


def test_sc2_estimator_recovers_synthetic_and_is_reported(runner, tmp_path):
    src, tgt, T_gt = _synthetic_pair(tmp_path)
    out = tmp_path / "T.txt"
    report = tmp_path / "r.json"
    args = ["register", str(src), str(tgt), "--features", "fpfh", "--voxel-size", "0.05"]
    res = runner.invoke(cli, [*args, "--estimator", "sc2", "-o", str(out), "--json", str(report)])
    assert res.exit_code == 0, res.output
    T = read_transform(out)
    assert _rotation_error_deg(T[:3, :3], T_gt[:3, :3]) < 2.0
    assert np.linalg.norm(T[:3, 3] - T_gt[:3, 3]) < 0.05
    assert json.loads(report.read_text())["recipe"]["fitting"]["estimator"] == "sc2"


def test_confidence_gate_exit_3(runner, random_weights, tmp_path):
    src, tgt, _ = _synthetic_pair(tmp_path)
    out = tmp_path / "T.txt"
    res = runner.invoke(
        cli,
        [
            "register",
            str(src),
            str(tgt),
            "--weights",
            str(random_weights),
            "--min-confidence",
            "1.0",
            "-o",
            str(out),
        ],
    )
    assert res.exit_code == 3
    assert "below --min-confidence" in res.stderr
    assert out.exists()  # registered: outputs are written, the exit code carries the verdict


def _surface_mm(xy: np.ndarray) -> np.ndarray:
    """A wavy surface 4 m across, in millimetres."""
    return np.column_stack([xy, 100 * np.sin(xy[:, 0] / 500)])


def _write(path: Path, content: bytes) -> Path:
    path.write_bytes(content)
    return path


BAD_INPUTS = {
    "missing": (lambda d: d / "nope.ply", "no such file"),
    "garbage": (lambda d: _write(d / "g.ply", b"\x00\x01garbage" * 10), "PLY"),
    "empty_npy": (lambda d: (np.save(d / "e.npy", np.zeros((0, 3))), d / "e.npy")[1], "empty"),
    "wrong_shape": (lambda d: (np.save(d / "w.npy", np.zeros((5, 2))), d / "w.npy")[1], "(5, 2)"),
    "all_nan": (
        lambda d: (np.save(d / "n.npy", np.full((9, 3), np.nan)), d / "n.npy")[1],
        "finite",
    ),
    "millimetres": (
        lambda d: (
            np.save(d / "mm.npy", _surface_mm(np.random.default_rng(0).uniform(0, 4000, (500, 2)))),
            d / "mm.npy",
        )[1],
        "same units",
    ),
    "too_few": (lambda d: (np.save(d / "f.npy", np.zeros((2, 3))), d / "f.npy")[1], "voxel"),
    "unknown_ext": (lambda d: _write(d / "x.foo", b"1 2 3\n"), "extension"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_exit_1_one_line_no_output(runner, tmp_path, case):
    make, phrase = BAD_INPUTS[case]
    bad = make(tmp_path)
    good, _, _ = _synthetic_pair(tmp_path)
    out, report, aligned = tmp_path / "T.txt", tmp_path / "r.json", tmp_path / "a.ply"
    res = runner.invoke(
        cli,
        [
            "register",
            str(bad),
            str(good),
            "--features",
            "fpfh",
            "-o",
            str(out),
            "--json",
            str(report),
            "--aligned",
            str(aligned),
        ],
    )
    assert res.exit_code == 1, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("byoc: error")]
    assert len(lines) == 1, res.stderr
    assert bad.name in lines[0] or case == "too_few"
    assert phrase in lines[0]
    assert not out.exists() and not report.exists() and not aligned.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".") or "tmp" in p.name]


def test_default_register_needs_no_open3d_and_fpfh_says_it_does(
    runner, random_weights, tmp_path, monkeypatch
):
    # the learned default (features, RANSAC, --refine multiscale) is plain PyTorch: it
    # registers with open3d unimportable; --features fpfh (Open3D's FPFH) says what is missing
    # in one line, exit 1, nothing written
    monkeypatch.setitem(sys.modules, "open3d", None)
    src, tgt, _ = _synthetic_pair(tmp_path)
    out, report = tmp_path / "T.txt", tmp_path / "r.json"
    args = ["register", str(src), str(tgt), "--weights", str(random_weights), "-o", str(out)]
    res = runner.invoke(cli, [*args, "--json", str(report)])
    assert res.exit_code == 0, res.output
    assert read_transform(out).shape == (4, 4)
    assert json.loads(report.read_text())["refine"] == "multiscale"
    out.unlink()
    report.unlink()
    res = runner.invoke(cli, [*args, "--json", str(report), "--features", "fpfh"])
    assert res.exit_code == 1, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("byoc: error")]
    assert len(lines) == 1 and "open3d" in lines[0], res.stderr
    assert not out.exists() and not report.exists()
    # the single-scale Open3D ICP is gone: a usage error that lists what there is
    res = runner.invoke(cli, [*args, "--refine", "icp"])
    assert res.exit_code == 2 and "'multiscale'" in res.stderr, res.stderr


def test_nan_points_dropped_with_warning(runner, tmp_path):
    src, tgt, _ = _synthetic_pair(tmp_path)
    from byoc_cli.io import read_point_cloud

    pts = read_point_cloud(src).points
    pts[:10] = np.nan
    np.save(tmp_path / "nan.npy", pts)
    res = runner.invoke(
        cli,
        [
            "register",
            str(tmp_path / "nan.npy"),
            str(tgt),
            "--features",
            "fpfh",
            "-o",
            str(tmp_path / "T.txt"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert "dropped 10 point(s)" in res.stderr


def test_scale_option_returns_transform_in_input_units(runner, tmp_path):
    src, tgt, T_gt = _synthetic_pair(tmp_path)
    from byoc_cli.io import read_point_cloud

    for name, path in (("src_mm.npy", src), ("tgt_mm.npy", tgt)):
        np.save(tmp_path / name, read_point_cloud(path).points * 1000.0)
    out = tmp_path / "T.txt"
    res = runner.invoke(
        cli,
        [
            "register",
            str(tmp_path / "src_mm.npy"),
            str(tmp_path / "tgt_mm.npy"),
            "--features",
            "fpfh",
            "--voxel-size",
            "0.05",
            "--estimator",
            "ransac",
            "--scale",
            "0.001",
            "-o",
            str(out),
            "--json",
            str(tmp_path / "r.json"),
        ],
    )
    assert res.exit_code == 0, res.output
    T = read_transform(out)
    assert np.linalg.norm(T[:3, 3] - T_gt[:3, 3] * 1000.0) < 50.0  # millimetres
    report = json.loads((tmp_path / "r.json").read_text())
    assert (report["unit"], report["voxel_size"]) == ("m", 0.05)  # --scale: metres are known
    assert "voxel 0.05 m" in res.stderr


def test_usage_errors_exit_2(runner, tmp_path):
    src, tgt, _ = _synthetic_pair(tmp_path)
    res = runner.invoke(cli, ["register", str(src), str(tgt), "--estimator", "magic"])
    assert res.exit_code == 2 and "--estimator" in res.stderr
    res = runner.invoke(cli, ["register", str(tmp_path / "d.png"), str(tgt)])
    assert res.exit_code == 2 and "--intrinsics" in res.stderr


def test_bad_weights_file_exit_1(runner, tmp_path):
    src, tgt, _ = _synthetic_pair(tmp_path)
    bad = _write(tmp_path / "w.safetensors", b"not weights at all")
    res = runner.invoke(
        cli, ["register", str(src), str(tgt), "--weights", str(bad), "-o", str(tmp_path / "T.txt")]
    )
    assert res.exit_code == 1
    assert "w.safetensors" in res.stderr and "safetensors" in res.stderr
    assert not (tmp_path / "T.txt").exists()


def test_help_states_convention(runner):
    res = runner.invoke(cli, ["register", "--help"])
    assert res.exit_code == 0
    assert "x_tgt = R x_src + t" in res.output


@pytest.mark.realdata
def test_depth_images_with_intrinsics_register_real_tum_frames(runner, shared_data, tmp_path):
    """Two real TUM depth PNGs (fr3 cabinet keyframes 0 and 1) + intrinsics.json -> T_gt."""
    from byoc_cli.io.rgbd import discover_sequences

    root = shared_data / "rgbd" / "tum_fr3_cabinet"
    seq = discover_sequences(root)[0]
    src, tgt = seq.frames[1], seq.frames[0]
    T_gt = np.linalg.inv(tgt.pose) @ src.pose  # camera 1 -> camera 0
    out = tmp_path / "T.txt"
    result = runner.invoke(
        cli,
        [
            "register",
            str(src.depth_path),
            str(tgt.depth_path),
            "--features",
            "fpfh",
            "--intrinsics",
            str(root / "intrinsics.json"),
            "--depth-scale",
            "5000",
            "-o",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    T = read_transform(out)
    assert _rotation_error_deg(T[:3, :3], T_gt[:3, :3]) < 5.0
    assert np.linalg.norm(T[:3, 3] - T_gt[:3, 3]) < 0.10


@pytest.mark.parametrize(
    ("features", "expected"),
    [("fpfh", (10000, "ransac", 2000, "none")), ("byoc", (5000, "ransac", 5000, "multiscale"))],
)
def test_per_feature_defaults_are_reported(runner, random_weights, tmp_path, features, expected):
    src, tgt, _ = _synthetic_pair(tmp_path)
    report = tmp_path / "r.json"
    args = ["register", str(src), str(tgt), "--features", features, "--json", str(report)]
    if features == "byoc":
        args += ["--weights", str(random_weights)]
    result = runner.invoke(cli, [*args, "-o", str(tmp_path / "T.txt")])
    assert result.exit_code in (0, 3), result.output
    r = json.loads(report.read_text())
    max_points, estimator, most_correspondences, refine = expected
    assert (r["max_points"], r["estimator"], r["refine"]) == (max_points, estimator, refine)
    assert 3 <= r["num_correspondences"] <= most_correspondences


def test_json_to_stdout_alone_writes_only_the_json(runner, tmp_path):
    src, tgt, _ = _synthetic_pair(tmp_path)
    res = runner.invoke(cli, ["register", str(src), str(tgt), "--features", "fpfh", "--json", "-"])
    assert res.exit_code == 0, res.stderr
    report = json.loads(res.stdout)  # the whole of stdout is one JSON document
    assert len(report["T_tgt_src"]) == 4
    both = runner.invoke(cli, ["register", str(src), str(tgt), "-o", "-", "--json", "-"])
    assert both.exit_code == 2 and "cannot both be stdout" in both.stderr


def test_success_prints_one_line_on_stderr_silenced_by_q(runner, random_weights, tmp_path):
    src, tgt, _ = _synthetic_pair(tmp_path)
    args = ["register", str(src), str(tgt), "--weights", str(random_weights)]
    res = runner.invoke(cli, [*args, "-o", str(tmp_path / "T.txt")])
    assert res.exit_code == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"byoc: registered {src} -> {tgt}: ")
    report = json.loads(runner.invoke(cli, [*args, "--json", "-"]).stdout)
    figures = (
        f"confidence {report['confidence']:.3f}, {report['num_inliers']}/"
        f"{report['num_correspondences']} inliers within "
        f"{100 * report['inlier_threshold']:.1f} cm, voxel {report['voxel_size']:g} m, "
    )
    assert figures in lines[0] and lines[0].endswith(" s")
    assert res.stdout == ""
    # the refinement's restarts ran, and the report says how they agreed
    assert {"restart_return", "restart_gain"} <= report["cues"].keys()
    assert 0.0 <= report["cues"]["restart_return"] <= 1.0 and "restarts" in report["timings_s"]
    # -q before or after the command's name silences it; stdout keeps only the matrix
    for quiet in (["-q", *args, "-o", "-"], [*args, "-o", "-", "-q"]):
        res = runner.invoke(cli, quiet)
        assert res.exit_code == 0 and res.stderr == ""
        assert len(res.stdout.strip().splitlines()) == 4
    # below the gate: a line says so, and -q leaves only the exit code and T
    strict = [*args, "-o", "-", "--min-confidence", "1"]
    res = runner.invoke(cli, strict)
    assert res.exit_code == 3 and "is below --min-confidence 1" in res.stderr
    res = runner.invoke(cli, [*strict, "-q"])
    assert (res.exit_code, res.stderr) == (3, "") and len(res.stdout.splitlines()) == 4


def test_dev_stdout_is_stdout_and_dev_stderr_is_refused(runner, random_weights, tmp_path):
    src, tgt, _ = _synthetic_pair(tmp_path)
    args = ["register", str(src), str(tgt), "--weights", str(random_weights), "-q"]
    res = runner.invoke(cli, [*args, "-o", "/dev/stdout"])
    assert res.exit_code == 0, res.stderr
    assert res.stdout == runner.invoke(cli, [*args, "-o", "-"]).stdout
    assert len(res.stdout.strip().splitlines()) == 4
    res = runner.invoke(cli, [*args, "-o", str(tmp_path / "T.txt"), "--json", "/dev/stdout"])
    assert res.exit_code == 0 and json.loads(res.stdout)["T_tgt_src"]
    both = runner.invoke(cli, [*args, "-o", "/dev/stdout", "--json", "-"])
    assert both.exit_code == 2 and "cannot both be stdout" in both.stderr
    # an option that takes no '-' refuses /dev/stdout; /dev/stderr carries the messages
    aligned = runner.invoke(cli, [*args, "-o", str(tmp_path / "V.txt"), "--aligned", "/dev/stdout"])
    assert aligned.exit_code == 0 and aligned.stdout_bytes.startswith(b"ply\n")  # as '-'
    for option, path, phrase in (
        ("--json", "/dev/stderr", "is standard error"),
        ("-o", "/dev/fd/2", "is standard error"),
    ):
        res = runner.invoke(cli, [*args, "-o", str(tmp_path / "U.txt"), option, path])
        lines = res.stderr.strip().splitlines()
        assert res.exit_code == 1 and len(lines) == 1, res.stderr
        assert lines[0].startswith(f"byoc: error: {path}: ") and phrase in lines[0]
    assert not (tmp_path / "U.txt").exists()


@pytest.mark.parametrize(
    ("options", "factors"),
    [
        ({}, ((None, None), False)),
        ({"scale": 0.001}, ((0.001, 0.001), True)),
        ({"source_scale": 0.001}, ((0.001, 1.0), False)),
        ({"target_scale": 0.01}, ((1.0, 0.01), False)),
        ({"scale": 0.001, "target_scale": 1.0}, ((0.001, 1.0), True)),
        ({"source_scale": 0.001, "target_scale": 0.01}, ((0.001, 0.01), True)),
    ],
)
def test_each_clouds_factor_to_metres(options, factors):
    from byoc_cli.cli.pairwise import cloud_factors

    assert cloud_factors(options) == factors


@pytest.mark.realdata
def test_tum_depth_images_read_the_depth_scale_of_their_layout(runner, shared_data, tmp_path):
    """fr1_xyz's PNGs beside depth.txt: TUM's 5000 without --depth-scale (the default 1000 made
    T's translation 5 times too long); a scale that puts the median depth outside 0.1-20 m is
    one line naming --depth-scale."""
    root = shared_data / "rgbd" / "tum_fr1_xyz"
    frames = sorted((root / "depth").iterdir())
    pair = [str(frames[0]), str(frames[5]), "--intrinsics", str(root / "intrinsics.json")]
    args = ["register", *pair, "--features", "fpfh"]
    runs = {}
    for name, extra in (("layout", []), ("given", ["--depth-scale", "5000"])):
        out, report = tmp_path / f"{name}.txt", tmp_path / f"{name}.json"
        res = runner.invoke(cli, [*args, *extra, "-o", str(out), "--json", str(report)])
        assert res.exit_code == 0, res.output
        runs[name] = (out.read_bytes(), json.loads(report.read_text()))
    assert runs["layout"][0] == runs["given"][0]
    assert runs["layout"][1]["depth_scale"] == [5000.0, 5000.0]
    assert runs["layout"][1]["unit"] == "m"
    for wrong in ("100", "200000"):  # median depth about 30 m, then 0.03 m
        res = runner.invoke(cli, [*args, "--depth-scale", wrong, "-o", str(tmp_path / "w.txt")])
        assert res.exit_code == 1, res.output
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and "--depth-scale" in lines[0] and "median depth" in lines[0]
        assert not (tmp_path / "w.txt").exists()


# ------------------------------------------------------------------ --init (issue 36)


def _room_files(tmp_path: Path) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    """A room of three boxes sampled twice, the source moved: ``(source, target, T_gt,
    guess)``, the guess 8 deg (about the source's centroid) and 20 cm off."""
    from tests.pipeline._rooms import ROOM, sample_boxes

    rng = np.random.default_rng(2)

    def sample(n: int) -> np.ndarray:
        return sample_boxes(ROOM, n, rng)

    import torch

    R = axis_angle_to_matrix(torch.tensor([0.1, 0.35, -0.05], dtype=torch.float64)).numpy()
    T_gt = np.eye(4)
    T_gt[:3, :3], T_gt[:3, 3] = R, [0.5, -0.3, 0.1]
    src_points = (sample(20_000) - T_gt[:3, 3]) @ R
    write_ply(tmp_path / "src.ply", src_points)
    write_ply(tmp_path / "tgt.ply", sample(20_000))
    turn = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(8.0)], dtype=torch.float64))
    c = R @ src_points.mean(0) + T_gt[:3, 3]
    P = np.eye(4)
    P[:3, :3] = turn.numpy()
    P[:3, 3] = c - P[:3, :3] @ c + [0.12, -0.16, 0.0]
    return tmp_path / "src.ply", tmp_path / "tgt.ply", T_gt, P @ T_gt


def test_init_registers_locally_and_reports_the_path_and_the_correction(runner, tmp_path):
    from byoc_cli.io import write_transform

    src, tgt, T_gt, guess = _room_files(tmp_path)
    write_transform(tmp_path / "init.txt", guess)
    out, report = tmp_path / "T.txt", tmp_path / "r.json"
    args = ["register", str(src), str(tgt), "--init", str(tmp_path / "init.txt")]
    res = runner.invoke(cli, [*args, "-o", str(out), "--json", str(report)])
    assert res.exit_code == 0, res.output
    T = read_transform(out)
    assert _rotation_error_deg(T[:3, :3], T_gt[:3, :3]) < 0.5
    assert np.linalg.norm(T[:3, 3] - T_gt[:3, 3]) < 0.01
    data = json.loads(report.read_text())
    assert data["path"] == "local" and data["features"] == "none"
    init = data["init"]
    assert init["file"] == str(tmp_path / "init.txt") and init["inside_trust_region"]
    assert init["correction"]["rotation_deg"] == pytest.approx(8.0, abs=0.5)
    assert init["correction"]["translation"] == pytest.approx(0.2, abs=0.01)
    assert init["trust_region"] == {"rotation_deg": 20.0, "translation": pytest.approx(0.5)}
    assert "from --init (local)" in res.stderr and "correction 8." in res.stderr
    # without --init the report says so too
    res = runner.invoke(cli, ["register", str(src), str(tgt), "--json", "-", "-q"])
    assert json.loads(res.stdout)["path"] == "global"
    assert json.loads(res.stdout)["init"] is None


def test_init_beyond_max_correction_exits_3_and_says_why(runner, tmp_path):
    from byoc_cli.io import write_transform

    src, tgt, _, guess = _room_files(tmp_path)
    write_transform(tmp_path / "init.txt", guess)
    out = tmp_path / "T.txt"
    args = ["register", str(src), str(tgt), "--init", str(tmp_path / "init.txt"), "-o", str(out)]
    res = runner.invoke(cli, [*args, "--max-correction", "4"])
    assert res.exit_code == 3, res.output
    assert "beyond --max-correction 4.0 deg / 50.0 cm" in res.stderr
    assert out.exists()  # written all the same, as below the gate
    res = runner.invoke(cli, [*args, "--max-correction", "30,0.05"])
    assert res.exit_code == 3 and "beyond --max-correction 30.0 deg / 5.0 cm" in res.stderr


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "init.txt"),
        ("1 0 0\n0 1 0\n0 0 1\n", "expected a 4x4 matrix"),
        ("1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n", "reflection"),
        ("not numbers\n", "not a numeric matrix"),
    ],
)
def test_a_bad_init_file_exits_1_naming_it_and_writes_nothing(runner, tmp_path, content, message):
    src, tgt, _, _ = _room_files(tmp_path)
    init = tmp_path / "init.txt"
    if content is not None:
        init.write_text(content)
    out, report = tmp_path / "T.txt", tmp_path / "r.json"
    args = ["register", str(src), str(tgt), "--init", str(init), "-o", str(out)]
    res = runner.invoke(cli, [*args, "--json", str(report)])
    assert res.exit_code == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("byoc: error:") and "init.txt" in lines[0]
    assert message in lines[0]
    assert not out.exists() and not report.exists()


def test_init_options_are_checked_as_usage_errors(runner, tmp_path):
    from byoc_cli.io import write_transform

    src, tgt, _, guess = _room_files(tmp_path)
    write_transform(tmp_path / "init.txt", guess)
    args = ["register", str(src), str(tgt)]
    res = runner.invoke(cli, [*args, "--max-correction", "10,0.2"])
    assert res.exit_code == 2 and "--max-correction and --init-mode go with --init" in res.stderr
    res = runner.invoke(cli, [*args, "--init-mode", "global"])
    assert res.exit_code == 2
    with_init = [*args, "--init", str(tmp_path / "init.txt")]
    for bad in ("abc", "-5", "10,nan", "10,0.2,3", ""):
        res = runner.invoke(cli, [*with_init, "--max-correction", bad])
        assert res.exit_code == 2 and "--max-correction" in res.stderr, bad
    res = runner.invoke(cli, [*with_init, "--init-mode", "nearby"])
    assert res.exit_code == 2 and "--init-mode" in res.stderr
    # -o may not overwrite the initial pose it reads
    res = runner.invoke(cli, [*with_init, "-o", str(tmp_path / "init.txt")])
    assert res.exit_code != 0 and read_transform(tmp_path / "init.txt") is not None


@pytest.mark.slow
def test_a_smooth_pair_is_registered_with_fpfh_and_the_report_says_why(runner, tmp_path):
    write_ply(tmp_path / "a.ply", smooth_scan(0) * 10)  # 2 m long: in the trained size
    write_ply(tmp_path / "b.ply", smooth_scan(1) * 10)
    report = tmp_path / "r.json"
    args = ["register", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "--json", str(report)]
    run = runner.invoke(cli, [*args, "-o", str(tmp_path / "T.txt")])
    assert run.exit_code == 0, run.output  # two samplings of one surface: the identity
    got = json.loads(report.read_text())
    assert got["features"] == "fpfh" and got["features_choice"]["first"] == "fpfh"
    assert got["features_choice"]["rough_share"][0] <= got["features_choice"]["smooth_share"]
    assert "restarts" not in got["timings_s"] and "first" in got["timings_s"]
    assert "(FPFH features: smooth surfaces," in run.stderr


@pytest.mark.parametrize("agree", [True, False])
def test_the_summary_line_says_whether_the_repeats_reproduced_a_smooth_result(agree):
    from types import SimpleNamespace

    from byoc_cli.cli.register import summary_line

    note = {"repeats": [{}, {}], "agree": agree, "model_confidence": 0.3}
    result = SimpleNamespace(
        path="global", confidence=0.74 if agree else 0.3, num_inliers=45,
        num_correspondences=2000, inlier_threshold=0.01, voxel_size=0.005, fallback=None,
        features="fpfh", features_choice={"first": "fpfh", "rough_share": [0.0, 0.01]},
        reproduced=note, init=None, retries=None,
    )  # fmt: skip
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")
    assert line.endswith("rough; reproduced by 2 repeats, confidence 0.300 before)") == agree
    assert line.endswith("rough; not reproduced by its 2 repeats)") != agree
    result.reproduced = None  # no repeats ran
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")
    assert line.endswith("(FPFH features: smooth surfaces, 0 % and 1 % rough)")


def test_the_summary_line_says_when_fpfh_went_first_for_a_small_object():
    from types import SimpleNamespace

    from byoc_cli.cli.register import summary_line

    choice = {"first": "fpfh", "rough_share": [0.4, 0.9], "smooth_share": 0.125}
    result = SimpleNamespace(
        path="global", confidence=0.9, num_inliers=45, num_correspondences=2000,
        inlier_threshold=0.01, voxel_size=0.005, fallback=None, features="fpfh",
        features_choice={**choice, "small_object": True}, reproduced=None, init=None,
        retries=None,
    )  # fmt: skip
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")
    assert line.endswith("(FPFH features: an object below the trained size, 40 % and 90 % rough)")
    result.features_choice = {**choice, "rough_share": [0.0, 0.1], "small_object": True}
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")  # smooth says why
    assert line.endswith("(FPFH features: smooth surfaces, 0 % and 10 % rough)")
    result.features_choice = {**choice, "rough_share": [], "small_object": True}
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")  # shares not measured
    assert line.endswith("(FPFH features: an object below the trained size)")
    result.features_choice = {**result.features_choice, "in_millimetres": True}
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, None)
    assert line.endswith("(FPFH features: an object below the trained size, read as millimetres)")


@pytest.mark.parametrize("used", [True, False])
def test_the_summary_line_says_when_coarser_features_registered_an_object(used):
    from types import SimpleNamespace

    from byoc_cli.cli.register import summary_line

    coarser = {"used": 1.4 if used else None, "first_confidence": 0.212, "tries": [{}]}
    choice = {"first": "fpfh", "rough_share": [], "small_object": True, "coarser": coarser}
    result = SimpleNamespace(
        path="global", confidence=0.7, num_inliers=45, num_correspondences=2000,
        inlier_threshold=0.01, voxel_size=0.005, fallback=None, features="fpfh",
        features_choice=choice, reproduced=None, init=None, retries=None,
    )  # fmt: skip
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")
    said = "; features at 1.4x the voxel, the first try reached confidence 0.212)"
    assert line.endswith(f"(FPFH features: an object below the trained size{said}") == used
    assert line.endswith("(FPFH features: an object below the trained size)") != used


@pytest.mark.parametrize("agree", [True, False])
def test_the_summary_line_says_whether_the_repeats_reproduced_a_fallback_result(agree):
    from types import SimpleNamespace

    from byoc_cli.cli.register import summary_line

    note = {"repeats": [{}, {}], "agree": agree, "model_confidence": 0.12}
    result = SimpleNamespace(
        path="global", confidence=0.85 if agree else 0.12, num_inliers=45,
        num_correspondences=2000, inlier_threshold=0.01, voxel_size=0.005, features="fpfh",
        fallback={"used": True, "features": "fpfh", "learned_confidence": 0.0},
        features_choice=None, reproduced=note, init=None, retries=None,
    )  # fmt: skip
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")
    head = "(FPFH features: the learned ones reached confidence 0.000"
    assert line.endswith(f"{head}; reproduced by 2 repeats, confidence 0.120 before)") == agree
    assert line.endswith(f"{head}; not reproduced by its 2 repeats)") != agree


def test_the_summary_line_says_when_a_retry_was_kept():
    from types import SimpleNamespace

    from byoc_cli.cli.register import summary_line

    result = SimpleNamespace(
        path="global", confidence=0.84, num_inliers=45, num_correspondences=5000,
        inlier_threshold=0.05, voxel_size=0.025, fallback=None, features="byoc",
        features_choice=None, reproduced=None, init=None,
        retries={"first_confidence": 0.12, "tries": [{}], "kept_seed": 1},
    )  # fmt: skip
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")
    assert line.endswith("(retry with seed 1: the first try reached confidence 0.120)")
    result.fallback = {"used": True, "features": "fpfh", "learned_confidence": 0.3}
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")  # FPFH's was kept
    assert line.endswith("(FPFH features: the learned ones reached confidence 0.300)")
    result.fallback, result.retries["kept_seed"] = None, None  # the first result was kept
    line = summary_line(Path("a.ply"), Path("b.ply"), result, 1.0, "m")
    assert line.endswith("voxel 0.025 m, 1.0 s")


def test_init_dash_reads_the_pose_from_stdin(runner, tmp_path):
    from byoc_cli.io import format_transform

    src, tgt, T_gt, guess = _room_files(tmp_path)
    out = tmp_path / "T.txt"
    args = ["register", str(src), str(tgt), "--init", "-", "-o", str(out), "-q"]
    res = runner.invoke(cli, args, input=format_transform(guess))
    assert res.exit_code == 0, res.output
    assert np.linalg.norm(read_transform(out)[:3, 3] - T_gt[:3, 3]) < 0.01
    res = runner.invoke(cli, args, input="1 2 3\n")
    assert res.exit_code == 1 and "stdin: expected a 4x4 matrix" in res.stderr
