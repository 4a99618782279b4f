"""Issue 36, item 2, as a user runs it: the demo pair as LAS in UTM coordinates, a LAZ copy and
a two-scan E57 registers as well as the same points in PLY near the origin, with T in the
input's coordinates; ``--aligned`` LAS keeps its header; bad LAS/E57 files are one line."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pye57
import pytest
from click.testing import CliRunner

from byoc_cli.api import load_cloud
from byoc_cli.cli.main import cli
from byoc_cli.io import read_transform, write_ply

#: offsets of a UTM zone (easting about 5e5, northing about 4e6) and a height
UTM = np.array([512345.678, 4123456.789, 123.4])
#: a survey export's header: 0.1 mm steps, offsets near the data
LAS_SCALE = 1e-4
LAS_OFFSETS = np.array([512000.0, 4123000.0, 0.0])


@pytest.fixture(scope="module")
def formats(shared_data: Path, tmp_path_factory) -> dict[str, tuple]:
    """The demo pair as PLY at the origin, LAS and LAZ in UTM coordinates (header offsets,
    an extra dimension, a VLR) and one E57 holding both as scans whose poses carry UTM."""
    demo = shared_data / "pairs" / "3dmatch_demo"
    src, tgt = load_cloud(demo / "source.ply"), load_cloud(demo / "target.ply")
    folder = tmp_path_factory.mktemp("formats")
    write_ply(folder / "s.ply", src)
    write_ply(folder / "t.ply", tgt)
    for name, points in (("s", src), ("t", tgt)):
        header = laspy.LasHeader(point_format=3, version="1.2")
        header.scales, header.offsets = np.full(3, LAS_SCALE), LAS_OFFSETS
        header.add_extra_dim(laspy.ExtraBytesParams(name="reflectance", type=np.float32))
        header.vlrs.append(laspy.VLR("byoc_test", 7, "kept", b"site 36"))
        las = laspy.LasData(header)
        las.x, las.y, las.z = (points + UTM).T
        las.intensity = np.arange(len(points)) % 60000
        las.reflectance = np.linspace(0, 1, len(points), dtype=np.float32)
        las.write(str(folder / f"{name}.las"))
        las.write(str(folder / f"{name}.laz"))
    with pye57.E57(str(folder / "pair.e57"), mode="w") as e57:
        for name, points in (("source", src), ("target", tgt)):
            data = {
                f"cartesian{a}": np.ascontiguousarray(points[:, j]) for j, a in enumerate("XYZ")
            }
            e57.write_scan_raw(data, name=name, rotation=np.array([1.0, 0, 0, 0]), translation=UTM)
    return {
        "ply": (folder / "s.ply", folder / "t.ply"),
        "las": (folder / "s.las", folder / "t.las"),
        "laz": (folder / "s.laz", folder / "t.laz"),
        "e57": (Path(f"{folder / 'pair.e57'}:0"), Path(f"{folder / 'pair.e57'}:1")),
        "T_gt": (np.loadtxt(demo / "T_gt.txt"),),
    }


def _register(pair, out: Path, *args) -> tuple[np.ndarray, dict, object]:
    report = out.with_suffix(".json")
    result = CliRunner().invoke(
        cli, ["register", str(pair[0]), str(pair[1]), "-o", str(out), "--json", str(report), *args]
    )
    assert result.exit_code == 0, result.output
    return read_transform(out), json.loads(report.read_text()), result


@pytest.fixture(scope="module")
def at_origin(formats, tmp_path_factory) -> tuple[np.ndarray, dict]:
    T, report, _ = _register(formats["ply"], tmp_path_factory.mktemp("origin") / "T.txt")
    return T, report


def _local(T_utm: np.ndarray) -> np.ndarray:
    """A T between the clouds in UTM coordinates as the T between the same clouds at the
    origin."""
    shift = np.eye(4)
    shift[:3, 3] = UTM
    return np.linalg.inv(shift) @ T_utm @ shift


def _difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Rotation (deg) and translation (cm) of ``inv(T_a) @ T_b``."""
    E = np.linalg.inv(T_a) @ T_b
    cos = np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(cos))), float(100 * np.linalg.norm(E[:3, 3]))


@pytest.mark.realdata
@pytest.mark.parametrize("fmt", ["las", "laz", "e57"])
def test_las_laz_and_e57_register_like_the_ply_at_the_origin(formats, at_origin, tmp_path, fmt):
    T_ply, report_ply = at_origin
    T_utm, report, _ = _register(formats[fmt], tmp_path / "T.txt")
    # T is in the input's coordinates: it maps UTM source points onto UTM target points
    assert np.abs(T_utm[:3, 3]).max() > 1e4
    T = _local(T_utm)
    (T_gt,) = formats["T_gt"]
    assert max(_difference(T, T_gt)[0] / 5, _difference(T, T_gt)[1] / 10) < 1  # 5 deg, 10 cm
    degrees, cm = _difference(T, T_ply)
    assert degrees < 0.5 and cm < 2, (degrees, cm)
    assert report["passed"] and abs(report["confidence"] - report_ply["confidence"]) < 0.05


@pytest.mark.realdata
def test_aligned_las_keeps_its_header_and_qc_files_are_written(formats, tmp_path):
    source, target = formats["laz"][0], formats["las"][1]
    aligned, qc = tmp_path / "moved.las", tmp_path / "qc" / "new"
    T, report, _ = _register(
        (source, target), tmp_path / "T.txt", "--aligned", str(aligned), "--qc", str(qc)
    )
    before, after = laspy.read(str(source)), laspy.read(str(aligned))
    assert after.header.point_format.id == before.header.point_format.id == 3
    np.testing.assert_array_equal(after.header.scales, before.header.scales)
    np.testing.assert_array_equal(after.header.offsets, LAS_OFFSETS)
    assert after.header.point_count == before.header.point_count
    assert list(after.point_format.extra_dimension_names) == ["reflectance"]
    assert any(v.user_id == "byoc_test" and v.record_data == b"site 36" for v in after.vlrs)
    np.testing.assert_array_equal(after.intensity, before.intensity)
    np.testing.assert_array_equal(after.reflectance, before.reflectance)
    expected = before.xyz @ T[:3, :3].T + T[:3, 3]
    assert np.abs(after.xyz - expected).max() <= LAS_SCALE / 2 + 1e-7
    assert not after.header.are_points_compressed
    png, ply = qc / "s__t_qc.png", qc / "s__t_residual.ply"
    assert png.stat().st_size > 10_000 and ply.stat().st_size > 10_000
    assert report["qc"]["png"] == str(png) and report["qc"]["unit"] == "m"
    assert 0.3 < report["qc"]["within_clip"] <= 1.0  # the demo pair overlaps about half


@pytest.mark.realdata
def test_register_scans_takes_each_scan_of_a_multi_scan_e57(formats, tmp_path):
    e57 = formats["e57"][0].parent / "pair.e57"
    out = tmp_path / "scans"
    result = CliRunner().invoke(cli, ["register-scans", str(e57), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (out / "poses").iterdir()) == ["pair_scan0.txt", "pair_scan1.txt"]
    report = json.loads((out / "report.json").read_text())
    assert [s["path"] for s in report["scans"]] == [f"{e57}:0", f"{e57}:1"]
    # world = scan 0 (the source): scan 1's pose is T_src_tgt, in the file's UTM coordinates
    T_world_tgt = read_transform(out / "poses" / "pair_scan1.txt")
    (T_gt,) = formats["T_gt"]
    degrees, cm = _difference(_local(np.linalg.inv(T_world_tgt)), T_gt)
    assert degrees < 5 and cm < 10, (degrees, cm)


@pytest.mark.realdata
def test_a_multi_scan_e57_given_to_register_says_how_to_pick_a_scan(formats, tmp_path):
    e57 = formats["e57"][0].parent / "pair.e57"
    out = tmp_path / "T.txt"
    result = CliRunner().invoke(cli, ["register", str(e57), str(formats["las"][1]), "-o", str(out)])
    assert result.exit_code == 1
    assert result.stderr == (
        f"byoc: error: {e57}: holds 2 scans; give one as {e57}:0 to {e57}:1 (0-based), or give "
        "the file to `byoc register-scans`, which takes each scan as a cloud\n"
    )
    assert not out.exists()


def _bad_las(folder: Path) -> Path:
    path = folder / "bad.las"
    path.write_bytes(b"LASF" + bytes(300))
    return path


def _truncated_laz(folder: Path) -> Path:
    header = laspy.LasHeader(point_format=0, version="1.2")
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.random.default_rng(0).uniform(0, 9, (5000, 3)).T
    las.write(str(folder / "full.laz"))
    data = (folder / "full.laz").read_bytes()
    (folder / "cut.laz").write_bytes(data[: len(data) // 2])
    return folder / "cut.laz"


def _bad_e57(folder: Path) -> Path:
    path = folder / "bad.e57"
    path.write_bytes(b"ASTM-E57" + bytes(3000))
    return path


@pytest.mark.parametrize(
    ("make", "phrase"),
    [
        (_bad_las, "not a LAS file"),
        (_truncated_laz, "truncated or corrupt LAZ point data"),
        (_bad_e57, "not a readable E57 file"),
    ],
)
def test_a_corrupt_file_is_one_line_naming_it_and_nothing_is_written(tmp_path, make, phrase):
    bad = make(tmp_path)
    good = tmp_path / "good.ply"
    write_ply(good, np.random.default_rng(1).uniform(0, 1, (500, 3)))
    outputs = [tmp_path / "T.txt", tmp_path / "moved.ply", tmp_path / "qc"]
    args = ["-o", str(outputs[0]), "--aligned", str(outputs[1]), "--qc", str(outputs[2])]
    result = CliRunner().invoke(cli, ["register", str(bad), str(good), *args])
    assert result.exit_code == 1
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"byoc: error: {bad}: {phrase}"), lines
    assert not any(p.exists() for p in outputs)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
