"""LAS/LAZ: georeferenced coordinates read in float64 with the header's scales and offsets,
bad files in one phrase, the moved source written into a copy of the source's records."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io import read_point_cloud
from byoc_cli.io.las import read_las_points, write_las_like

#: a UTM easting, northing and height
UTM = np.array([512345.678, 4123456.789, 123.4])
SCALE = 0.001


def _points(n: int = 2000, seed: int = 0) -> np.ndarray:
    """A few metres of points around :data:`UTM`, on the header's 1 mm grid."""
    rng = np.random.default_rng(seed)
    local = np.round(rng.uniform(-5, 5, (n, 3)) / SCALE) * SCALE
    return UTM + local


def _write_las(path: Path, points: np.ndarray, *, version: str = "1.4", fmt: int = 6) -> Path:
    """A LAS/LAZ file (by extension) with offsets near the data, 1 mm scales, intensity, an
    extra dimension and a VLR, as a survey export has."""
    header = laspy.LasHeader(point_format=fmt, version=version)
    header.scales = np.full(3, SCALE)
    header.offsets = np.array([512000.0, 4123000.0, 0.0])
    header.add_extra_dim(laspy.ExtraBytesParams(name="reflectance", type=np.float32))
    header.vlrs.append(laspy.VLR("byoc_test", 42, "a test record", b"kept as it is"))
    las = laspy.LasData(header)
    las.x, las.y, las.z = points.T
    las.intensity = np.arange(len(points), dtype=np.uint16)
    las.classification = np.full(len(points), 2, dtype=np.uint8)
    las.reflectance = np.linspace(0, 1, len(points), dtype=np.float32)
    las.write(str(path))
    return path


@pytest.fixture
def utm_las(tmp_path) -> tuple[Path, Path, np.ndarray]:
    points = _points()
    return _write_las(tmp_path / "a.las", points), _write_las(tmp_path / "a.laz", points), points


def test_las_and_laz_give_the_georeferenced_coordinates_in_float64(utm_las):
    las, laz, points = utm_las
    for path in (las, laz):
        got = read_las_points(path)
        assert got.dtype == np.float64 and got.shape == points.shape
        np.testing.assert_array_equal(got, laspy.read(str(path)).xyz)  # laspy's own scaling
        assert np.abs(got - points).max() < 1e-6  # mm on the grid: nothing went through float32
    loaded = read_point_cloud(laz)
    assert loaded.num_nonfinite_dropped == 0 and loaded.path == laz
    np.testing.assert_array_equal(loaded.points, read_las_points(las))


def test_every_point_format_and_version_reads(tmp_path):
    points = _points(300)
    for version, fmt in (("1.2", 0), ("1.2", 3), ("1.4", 8)):
        path = _write_las(tmp_path / f"v{version}_f{fmt}.las", points, version=version, fmt=fmt)
        assert np.abs(read_las_points(path) - points).max() < 1e-6


def test_extension_case_does_not_matter(utm_las, tmp_path):
    las, _, points = utm_las
    upper = tmp_path / "A.LAS"
    upper.write_bytes(las.read_bytes())
    assert np.abs(read_point_cloud(upper).points - points).max() < 1e-6


@pytest.mark.parametrize(
    ("case", "phrase"),
    [
        ("garbage", "not a LAS file"),
        ("truncated las", "truncated LAS file (header says 2000 points, the data holds"),
        ("truncated laz", "truncated or corrupt LAZ point data"),
        ("no points", "empty point cloud (0 points)"),
        ("empty file", "not a LAS file"),
    ],
)
def test_a_bad_file_is_one_phrase_naming_it(utm_las, tmp_path, case, phrase):
    las, laz, _ = utm_las
    made = {
        "garbage": ("g.las", b"LASF" + b"\x00" * 300),
        "truncated las": ("t.las", las.read_bytes()[: las.stat().st_size // 2]),
        "truncated laz": ("t.laz", laz.read_bytes()[: laz.stat().st_size // 2]),
        "empty file": ("e.las", b""),
    }
    if case == "no points":
        path = _write_las(tmp_path / "none.las", np.zeros((0, 3)))
    else:
        name, data = made[case]
        path = tmp_path / name
        path.write_bytes(data)
    with pytest.raises(InputError) as info:
        read_point_cloud(path)
    assert info.value.path == str(path)
    assert phrase in info.value.problem, info.value.problem
    assert "\n" not in str(info.value)


def _corrupted(laz: Path, case: str) -> bytes:
    """``laz``'s bytes with one field of its header, LASzip record or chunk table made huge."""
    import struct

    data = bytearray(laz.read_bytes())
    offset = struct.unpack("<I", data[96:100])[0]
    if case == "records":  # the number of VLRs
        data[100:104] = struct.pack("<I", 3_776_826_671)
    elif case == "chunk size":  # the LASzip record's chunk size (50,000 as written)
        at = data.find(struct.pack("<I", 50_000), 0, offset)
        data[at : at + 4] = struct.pack("<I", 0x7FFFFFFF)
    elif case == "chunk count":  # the number of chunks in the chunk table
        table = struct.unpack("<q", data[offset : offset + 8])[0]
        data[table + 4 : table + 8] = struct.pack("<I", 1_863_783_250)
    elif case == "chunk table offset":  # bytes inserted before the table: it points elsewhere
        data[offset + 20 : offset + 20] = bytes(range(14))
    return bytes(data)


@pytest.mark.parametrize("case", ["records", "chunk size", "chunk count", "chunk table offset"])
def test_a_corrupt_count_is_refused_before_laspy_or_lazrs_allocates_for_it(utm_las, tmp_path, case):
    # lazrs sized its buffers by these fields and aborted the process (allocations of 30 to
    # 49 GB), or laspy looped over 3.8e9 records: read in a child under a 2 GB bound
    _, laz, _ = utm_las
    bad = tmp_path / "bad.laz"
    bad.write_bytes(_corrupted(laz, case))
    code = (
        "import sys\n"
        "from byoc_cli.errors import InputError\n"
        "from byoc_cli.io import read_point_cloud\n"
        "try:\n    read_point_cloud(sys.argv[1])\n"
        "except InputError as e:\n    print(e.problem)\n"
    )
    run = subprocess.run(
        ["bash", "-c", 'ulimit -v 2000000; exec "$0" -c "$1" "$2"', sys.executable, code, bad],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr[-500:]
    assert run.stdout.startswith(("corrupt LAS header", "truncated or corrupt LAZ point data"))


def test_missing_laspy_or_lazrs_is_an_install_hint(utm_las, monkeypatch):
    las, laz, points = utm_las
    # a fresh interpreter where lazrs cannot be imported, as on an install without it
    script = (
        "import sys; sys.modules['lazrs'] = None\n"
        "import numpy as np\n"
        "from byoc_cli.errors import InputError\n"
        "from byoc_cli.io.las import read_las_points, write_las_like\n"
        "print(read_las_points(sys.argv[1]).shape)\n"
        "for call in (lambda: read_las_points(sys.argv[2]),\n"
        "             lambda: write_las_like(sys.argv[3], sys.argv[1], np.load(sys.argv[4]))):\n"
        "    try:\n"
        "        call()\n"
        "    except InputError as exc:\n"
        "        print(exc)\n"
    )
    np.save(laz.with_suffix(".npy"), points)
    out = laz.parent / "out.laz"
    run = subprocess.run(
        [sys.executable, "-c", script, las, laz, out, laz.with_suffix(".npy")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0] == "(2000, 3)"  # plain LAS needs no backend
    assert lines[1] == f"{laz}: reading LAZ needs the lazrs backend; install it with " + (
        "`pip install 'laspy[lazrs]'`"
    )
    assert lines[2].startswith(f"{out}: writing LAZ needs the lazrs backend; install it")
    assert not out.exists()
    monkeypatch.setitem(sys.modules, "lazrs", None)  # lazrs gone after laspy loaded it
    with pytest.raises(InputError, match=r"needs the lazrs backend; install it with"):
        read_las_points(laz)
    monkeypatch.setitem(sys.modules, "laspy", None)
    with pytest.raises(InputError, match=r"a\.las: reading LAS/LAZ needs laspy; install it"):
        read_las_points(las)


def _moved(points: np.ndarray, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    angle = np.radians(10.0)
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    centre = points.mean(axis=0)
    return (points - centre) @ R.T + centre + np.asarray(shift)


@pytest.mark.parametrize("out_name", ["moved.las", "moved.laz"])
def test_the_moved_source_keeps_its_header_and_records(utm_las, tmp_path, out_name):
    las_path, _, points = utm_las
    moved = _moved(points, (1.5, -2.0, 0.25))
    out = tmp_path / out_name
    write_las_like(out, las_path, moved)
    before, after = laspy.read(str(las_path)), laspy.read(str(out))
    assert after.header.point_format.id == before.header.point_format.id
    assert str(after.header.version) == str(before.header.version)
    np.testing.assert_array_equal(after.header.scales, before.header.scales)
    np.testing.assert_array_equal(after.header.offsets, before.header.offsets)
    assert after.header.point_count == before.header.point_count == len(points)
    assert list(after.point_format.extra_dimension_names) == ["reflectance"]
    assert [
        (v.user_id, v.record_id, v.record_data)
        for v in after.header.vlrs
        if v.user_id == "byoc_test"
    ] == [("byoc_test", 42, b"kept as it is")]
    for name in ("intensity", "classification", "reflectance", "gps_time", "return_number"):
        np.testing.assert_array_equal(after[name], before[name])
    assert np.abs(after.xyz - moved).max() <= SCALE / 2 + 1e-9  # one rounding to the grid
    np.testing.assert_allclose(after.header.mins, after.xyz.min(axis=0))
    np.testing.assert_allclose(after.header.maxs, after.xyz.max(axis=0))
    assert after.header.are_points_compressed == (out.suffix == ".laz")


def test_offsets_move_only_when_the_coordinates_no_longer_fit(utm_las, tmp_path):
    las_path, _, points = utm_las
    far = points + np.array([3.0e6, 0.0, 0.0])  # 3000 km east: past int32 at 1 mm steps
    write_las_like(tmp_path / "far.las", las_path, far)
    after = laspy.read(str(tmp_path / "far.las"))
    np.testing.assert_array_equal(after.header.scales, np.full(3, SCALE))
    assert after.header.offsets[0] != 512000.0
    assert np.abs(after.xyz - far).max() <= SCALE / 2 + 1e-6


def test_points_that_do_not_match_the_source_are_refused(utm_las, tmp_path):
    las_path, _, points = utm_las
    out = tmp_path / "x.las"
    with pytest.raises(ShapeError, match=r"\(2000, 3\)"):
        write_las_like(out, las_path, points[:-1])
    spread = points.copy()
    spread[0, 0] += 1e7  # 1e10 steps of 1 mm between two points: no offset holds both
    with pytest.raises(ShapeError, match="int32"):
        write_las_like(out, las_path, spread)
    with pytest.raises(InputError, match="the folder does not exist"):
        write_las_like(tmp_path / "missing" / "x.las", las_path, points)
    assert not out.exists() and not list(tmp_path.glob(".x.las*"))
