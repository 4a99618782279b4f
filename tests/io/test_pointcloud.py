"""Point-cloud files: PLY/NPY/PCD/XYZ in, binary PLY out, and every error naming the file."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import plyfile
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import DependencyError, InputError, ShapeError, require_open3d
from byoc_cli.io import SUPPORTED_EXTENSIONS, LoadedCloud, check_units, read_point_cloud, write_ply
from byoc_cli.io import inputs as inputs_module


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture
def o3d():
    try:
        return require_open3d()
    except DependencyError as exc:
        pytest.skip(str(exc))


@pytest.fixture
def no_open3d(monkeypatch):
    """Make ``import open3d`` fail, as on a machine without it."""
    monkeypatch.setitem(sys.modules, "open3d", None)


def _error(path, fmt=None):
    """The InputError that reading ``path`` raises; checks that it names the file."""
    with pytest.raises(InputError) as info:
        read_point_cloud(path, fmt)
    assert info.value.path == str(path)
    assert str(info.value) == f"{path}: {info.value.problem}"
    return info.value.problem


def _ply_bytes(header_lines, body: bytes, fmt="binary_little_endian") -> bytes:
    head = "\n".join(["ply", f"format {fmt} 1.0", *header_lines, "end_header"]) + "\n"
    return head.encode("ascii") + body


# ---------------------------------------------------------------- write_ply round trips


def test_write_ply_round_trip_float32_and_float64(tmp_path, rng):
    points = rng.normal(size=(1000, 3)) * 10
    write_ply(tmp_path / "f.ply", points)
    write_ply(tmp_path / "d.ply", points, dtype=np.float64)
    f32 = read_point_cloud(tmp_path / "f.ply")
    f64 = read_point_cloud(tmp_path / "d.ply")
    assert isinstance(f32, LoadedCloud)
    assert f32.points.dtype == np.float64 and f32.points.shape == (1000, 3)
    assert np.array_equal(f32.points, points.astype(np.float32).astype(np.float64))
    assert np.array_equal(f64.points, points)
    assert f64.num_nonfinite_dropped == 0 and f64.path == tmp_path / "d.ply"
    assert f64.points.flags.writeable and f64.points.flags.c_contiguous
    header = plyfile.PlyData.read(str(tmp_path / "d.ply"))
    assert header.byte_order == "<" and not header.text
    assert [p.name for p in header["vertex"].properties] == ["x", "y", "z"]
    assert header["vertex"].properties[0].val_dtype in ("f8", "<f8")


def test_write_ply_colors_normals(tmp_path, rng):
    points = rng.normal(size=(50, 3))
    normals = rng.normal(size=(50, 3))
    colors = rng.integers(0, 256, size=(50, 3))  # int64 in range is accepted
    write_ply(tmp_path / "c.ply", points, colors=colors, normals=normals)
    data = plyfile.PlyData.read(str(tmp_path / "c.ply"))["vertex"].data
    assert data.dtype.names == ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue")
    assert np.array_equal(np.stack([data["red"], data["green"], data["blue"]], 1), colors)
    assert np.allclose(np.stack([data["nx"], data["ny"], data["nz"]], 1), normals, atol=1e-6)
    assert np.allclose(read_point_cloud(tmp_path / "c.ply").points, points, atol=1e-6)


def test_write_ply_bad_arguments(tmp_path):
    with pytest.raises(ShapeError):
        write_ply(tmp_path / "a.ply", np.zeros((4, 2)))
    with pytest.raises(ShapeError):
        write_ply(tmp_path / "a.ply", np.zeros((4, 3)), colors=np.zeros((3, 3), np.uint8))
    with pytest.raises(ShapeError):
        write_ply(tmp_path / "a.ply", np.zeros((4, 3)), colors=np.full((4, 3), 300))
    with pytest.raises(ShapeError):
        write_ply(tmp_path / "a.ply", np.zeros((4, 3)), normals=np.zeros((4, 2)))
    with pytest.raises(ShapeError):
        write_ply(tmp_path / "a.ply", np.zeros((4, 3)), dtype=np.float16)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InputError, match="folder does not exist"):
        write_ply(tmp_path / "no" / "a.ply", np.zeros((4, 3)))


def test_write_ply_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "a.ply"
    path.write_bytes(b"old")

    def boom(self, stream):
        stream.write(b"ply\nformat binary")
        raise RuntimeError("crash mid-write")

    monkeypatch.setattr(plyfile.PlyData, "write", boom)
    with pytest.raises(RuntimeError):
        write_ply(path, np.zeros((4, 3)))
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.ply"]


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(1, 40),
    seed=st.integers(0, 2**32 - 1),
    big_endian=st.booleans(),
    text=st.booleans(),
)
def test_round_trip_property_all_encodings(tmp_path_factory, n, seed, big_endian, text):
    points = np.random.default_rng(seed).normal(size=(n, 3)) * 1e3
    vertex = np.empty(n, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    for j, k in enumerate("xyz"):
        vertex[k] = points[:, j]
    path = tmp_path_factory.mktemp("p") / "c.ply"
    element = plyfile.PlyElement.describe(vertex, "vertex")
    plyfile.PlyData([element], text=text, byte_order=">" if big_endian else "<").write(str(path))
    assert np.array_equal(read_point_cloud(path).points, points)


# ---------------------------------------------------------------- hand-written PLY files


def test_ascii_ply_with_extra_properties_and_faces(tmp_path):
    path = tmp_path / "mesh.ply"
    path.write_text(
        textwrap.dedent(
            """\
            ply
            format ascii 1.0
            comment made by hand
            element vertex 4
            property uchar intensity
            property float x
            property float y
            property double z
            property uchar red
            element face 2
            property list uchar int vertex_indices
            end_header
            7 0 0 0 255
            7 1 0 0.5 255
            7 0 1 -1e2 0
            7 1.5 1 nan 0
            3 0 1 2
            4 0 1 2 3
            """
        )
    )
    cloud = read_point_cloud(path)
    assert np.array_equal(cloud.points, [[0, 0, 0], [1, 0, 0.5], [0, 1, -100]])
    assert cloud.num_nonfinite_dropped == 1


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("kind", ["f4", "f8", "i4"])
def test_binary_ply_byte_orders_and_types(tmp_path, order, kind):
    points = np.array([[1.5, -2.0, 3.25], [0.0, 1e3, -7.0]])
    if kind == "i4":
        points = np.round(points)
    fields = [("nx", "f4"), ("x", kind), ("y", kind), ("z", kind), ("flags", "u2")]
    dtype = np.dtype([(name, order + code) for name, code in fields])
    records = np.zeros(2, dtype=dtype)
    for j, k in enumerate("xyz"):
        records[k] = points[:, j]
    ply_type = {"f4": "float", "f8": "double", "i4": "int"}[kind]
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    lines = ["element vertex 2", "property float nx"]
    lines += [f"property {ply_type} {k}" for k in "xyz"] + ["property ushort flags"]
    path = tmp_path / "c.ply"
    path.write_bytes(_ply_bytes(lines, records.tobytes(), fmt))
    assert np.array_equal(read_point_cloud(path).points, points)


def test_binary_mesh_faces_after_and_before_vertices(tmp_path):
    points = np.arange(12, dtype="<f4").reshape(4, 3)
    faces = (
        np.array([3], "u1").tobytes()
        + np.array([0, 1, 2], "<i4").tobytes()
        + np.array([4], "u1").tobytes()
        + np.array([0, 1, 2, 3], "<i4").tobytes()
    )
    vertex_lines = ["element vertex 4", "property float x", "property float y", "property float z"]
    face_lines = ["element face 2", "property list uchar int vertex_indices"]
    after = tmp_path / "after.ply"
    after.write_bytes(_ply_bytes(vertex_lines + face_lines, points.tobytes() + faces))
    before = tmp_path / "before.ply"  # faces first: the general (plyfile) path
    before.write_bytes(_ply_bytes(face_lines + vertex_lines, faces + points.tobytes()))
    scalar_first = tmp_path / "scalar_first.ply"  # a scalar element before the vertices
    camera = np.array([1.0, 2.0], "<f8").tobytes()
    cam_lines = ["element camera 1", "property double a", "property double b"]
    scalar_first.write_bytes(_ply_bytes(cam_lines + vertex_lines, camera + points.tobytes()))
    for path in (after, before, scalar_first):
        assert np.array_equal(read_point_cloud(path).points, points), path.name
    cut = tmp_path / "cut_before.ply"  # truncated on the general path
    cut.write_bytes(before.read_bytes()[:-7])
    assert _error(cut).startswith("truncated PLY file (element 'vertex': row 3")


def test_ascii_ply_with_element_before_vertices(tmp_path):
    path = tmp_path / "c.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
        "element vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        "3 0 1 1\n1 2 3\n4 5 6\n"
    )
    assert np.array_equal(read_point_cloud(path).points, [[1, 2, 3], [4, 5, 6]])


def test_crlf_header_and_uppercase_extension(tmp_path):
    path = tmp_path / "C.PLY"
    path.write_bytes(
        b"ply\r\nformat ascii 1.0\r\nelement vertex 1\r\nproperty float x\r\n"
        b"property float y\r\nproperty float z\r\nend_header\r\n1 2 3\r\n"
    )
    assert np.array_equal(read_point_cloud(path).points, [[1, 2, 3]])


# ---------------------------------------------------------------- errors


def test_file_system_errors(tmp_path, monkeypatch):
    assert _error(tmp_path / "missing.ply") == "no such file"
    assert _error(tmp_path / "nodir" / "missing.ply") == "no such file"
    (tmp_path / "dir.ply").mkdir()
    assert _error(tmp_path / "dir.ply") == "is a directory"
    (tmp_path / "empty.ply").write_bytes(b"")
    assert _error(tmp_path / "empty.ply") == "empty file (0 bytes)"
    locked = tmp_path / "locked.ply"
    write_ply(locked, np.zeros((2, 3)))

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(inputs_module, "_open_fd", denied)
    assert _error(locked) == "permission denied"


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root reads anything")
def test_permission_denied_for_real(tmp_path):
    locked = tmp_path / "locked.ply"
    write_ply(locked, np.zeros((2, 3)))
    locked.chmod(0)
    assert _error(locked) == "permission denied"


def test_extensions(tmp_path):
    (tmp_path / "c.foo").write_text("1 2 3\n")
    problem = _error(tmp_path / "c.foo")
    assert problem == f"unsupported extension '.foo' (supported: {', '.join(SUPPORTED_EXTENSIONS)})"
    (tmp_path / "noext").write_text("1 2 3\n")
    assert _error(tmp_path / "noext").startswith("no file extension to tell the format")
    assert _error(tmp_path / "noext", "stl").startswith("unsupported format 'stl'")


PLY_HEAD = "ply\nformat binary_little_endian 1.0\n"
XYZ_PROPS = "property float x\nproperty float y\nproperty float z\n"
BAD_PLY = {
    "not ply": (b"solid cube\nfacet normal 0 0 1\n", "not a PLY file (bad header)"),
    "binary junk": (bytes(range(256)) * 4, "not a PLY file (bad header)"),
    "bad format": (b"ply\nformat binary_middle_endian 1.0\n", "bad PLY header (line 2:"),
    "bad type": (
        (PLY_HEAD + "element vertex 1\nproperty float128 x\nend_header\n").encode(),
        "bad PLY header (line 4:",
    ),
    "no end": ((PLY_HEAD + "element vertex 1\n" + XYZ_PROPS).encode(), "bad PLY header"),
    "no vertex": (
        (PLY_HEAD + "element point 1\n" + XYZ_PROPS + "end_header\n").encode() + bytes(12),
        "PLY has no vertex element",
    ),
    "no z": (
        (PLY_HEAD + "element vertex 1\nproperty float x\nproperty float y\nend_header\n").encode()
        + bytes(8),
        "vertex element lacks x, y, z properties (missing z)",
    ),
    "zero vertices": (
        (PLY_HEAD + "element vertex 0\n" + XYZ_PROPS + "end_header\n").encode(),
        "empty point cloud (0 points)",
    ),
    "truncated binary": (
        (PLY_HEAD + "element vertex 10\n" + XYZ_PROPS + "end_header\n").encode()
        + bytes(12 * 4 + 5),
        "truncated PLY file (header says 10 vertices, data holds 4)",
    ),
    "truncated ascii": (
        b"ply\nformat ascii 1.0\nelement vertex 3\n" + XYZ_PROPS.encode() + b"end_header\n1 2 3\n",
        "truncated PLY file (header says 3 vertices, found 1)",
    ),
    "malformed ascii": (
        b"ply\nformat ascii 1.0\nelement vertex 2\n"
        + XYZ_PROPS.encode()
        + b"end_header\n1 2 3\n1 two 3\n",
        "malformed ASCII PLY vertex data",
    ),
    "all nan": (
        b"ply\nformat ascii 1.0\nelement vertex 4\n"
        + XYZ_PROPS.encode()
        + b"end_header\nnan 0 0\n0 inf 0\n0 0 -inf\nnan nan nan\n",
        "no finite points (all 4 points have NaN or Inf coordinates)",
    ),
}


@pytest.mark.parametrize("name", sorted(BAD_PLY))
def test_bad_ply_files(tmp_path, name):
    content, problem = BAD_PLY[name]
    path = tmp_path / f"{name.replace(' ', '_')}.ply"
    path.write_bytes(content)
    assert _error(path).startswith(problem)


def test_truncated_real_fragment_is_an_input_error(shared_data, tmp_path):
    real = (
        shared_data / "3dmatch" / "sample" / "3DMatch" / "7-scenes-redkitchen" / "cloud_bin_0.ply"
    )
    data = real.read_bytes()
    path = tmp_path / "cut.ply"
    path.write_bytes(data[: len(data) // 3])
    assert _error(path).startswith("truncated PLY file (header says 258342 vertices")


def test_nan_points_are_dropped_and_counted(tmp_path, rng):
    points = rng.normal(size=(100, 3))
    points[[3, 50, 99], [0, 1, 2]] = [np.nan, np.inf, -np.inf]
    write_ply(tmp_path / "c.ply", points, dtype=np.float64)
    cloud = read_point_cloud(tmp_path / "c.ply")
    assert cloud.num_nonfinite_dropped == 3
    assert np.array_equal(cloud.points, np.delete(points, [3, 50, 99], axis=0))


# ---------------------------------------------------------------- NPY


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16, np.uint8])
def test_npy_dtypes(tmp_path, dtype):
    points = np.arange(12).reshape(4, 3).astype(dtype)
    np.save(tmp_path / "c.npy", points)
    cloud = read_point_cloud(tmp_path / "c.npy")
    assert cloud.points.dtype == np.float64
    assert np.array_equal(cloud.points, points.astype(np.float64))
    np.save(tmp_path / "f.npy", np.asfortranarray(points.astype(np.float64)))
    assert read_point_cloud(tmp_path / "f.npy").points.flags.c_contiguous


def test_npy_errors(tmp_path):
    cases = {
        "n2": (np.zeros((5, 2)), "NPY array has shape (5, 2), expected (N, 3)"),
        "flat": (np.zeros(9), "NPY array has shape (9,), expected (N, 3)"),
        "n4": (np.zeros((5, 4)), "NPY array has shape (5, 4), expected (N, 3)"),
        "batch": (np.zeros((2, 5, 3)), "NPY array has shape (2, 5, 3), expected (N, 3)"),
        "empty": (np.zeros((0, 3)), "empty point cloud (0 points)"),
        "bool": (np.zeros((5, 3), bool), "NPY array has dtype bool, expected float or int"),
        "complex": (np.zeros((5, 3), complex), "NPY array has dtype complex128, expected"),
        "nan": (np.full((2, 3), np.nan), "no finite points (all 2 points"),
    }
    for name, (array, problem) in cases.items():
        path = tmp_path / f"{name}.npy"
        np.save(path, array)
        assert _error(path).startswith(problem), name
    objects = tmp_path / "objects.npy"
    np.save(objects, np.array([[1, 2, None]] * 2, dtype=object), allow_pickle=True)
    assert _error(objects) == "NPY array has dtype object, expected float or int"
    np.save(tmp_path / "good.npy", np.zeros((1000, 3)))
    data = (tmp_path / "good.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[:500])
    assert _error(tmp_path / "cut.npy").startswith("truncated or corrupt NPY file")
    (tmp_path / "text.npy").write_text("1 2 3\n")
    assert _error(tmp_path / "text.npy") == "not an NPY file (bad header)"
    pickled = tmp_path / "pickle.npy"
    import pickle

    pickled.write_bytes(pickle.dumps([[1.0, 2.0, 3.0]]))
    assert _error(pickled) == "not an NPY file (bad header)"


def test_format_override(tmp_path):
    np.save(tmp_path / "c.npy", np.ones((3, 3)))
    os.replace(tmp_path / "c.npy", tmp_path / "c.bin")
    assert read_point_cloud(tmp_path / "c.bin", fmt="NPY").points.shape == (3, 3)
    assert read_point_cloud(tmp_path / "c.bin", fmt=".npy").points.shape == (3, 3)


# ---------------------------------------------------------------- without open3d


def test_ply_npy_depth_free_of_open3d(tmp_path, no_open3d):
    with pytest.raises(DependencyError):
        require_open3d()
    write_ply(tmp_path / "c.ply", np.ones((3, 3)))
    np.save(tmp_path / "c.npy", np.ones((3, 3)))
    assert read_point_cloud(tmp_path / "c.ply").points.shape == (3, 3)
    assert read_point_cloud(tmp_path / "c.npy").points.shape == (3, 3)
    (tmp_path / "c.pcd").write_text("whatever")
    (tmp_path / "c.xyz").write_text("1 2 3\n")
    with pytest.raises(DependencyError):
        read_point_cloud(tmp_path / "c.xyz")


def test_io_package_imports_no_open3d():
    code = "import sys, byoc_cli.io; assert 'open3d' not in sys.modules, 'open3d imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


# ---------------------------------------------------------------- PCD and XYZ via open3d


def _o3d_cloud(o3d, points):
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(points)
    return cloud


@pytest.mark.parametrize("encoding", ["binary", "ascii", "binary_compressed"])
def test_pcd_written_by_open3d(tmp_path, o3d, rng, encoding):
    points = rng.normal(size=(500, 3))
    points[7] = np.nan
    path = tmp_path / "c.pcd"
    o3d.io.write_point_cloud(
        str(path),
        _o3d_cloud(o3d, points),
        write_ascii=encoding == "ascii",
        compressed=encoding == "binary_compressed",
    )
    assert f"DATA {encoding}" in path.read_bytes()[:400].decode("ascii", "replace")
    cloud = read_point_cloud(path)
    assert cloud.num_nonfinite_dropped == 1
    assert np.allclose(cloud.points, np.delete(points, 7, axis=0), atol=1e-6)


def test_pcd_by_hand_with_extra_fields(tmp_path, o3d):
    path = tmp_path / "c.pcd"
    path.write_text(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity\n"
        "SIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n1 2 3 9\n4 5 6 9\n"
    )
    assert np.array_equal(read_point_cloud(path).points, [[1, 2, 3], [4, 5, 6]])


def test_pcd_errors(tmp_path, o3d, rng, capfd):
    good = tmp_path / "good.pcd"
    o3d.io.write_point_cloud(str(good), _o3d_cloud(o3d, rng.normal(size=(1000, 3))))
    data = good.read_bytes()
    (tmp_path / "cut.pcd").write_bytes(data[: len(data) // 2])
    assert _error(tmp_path / "cut.pcd").startswith("truncated PCD file (header says 1000 points")
    ascii_pcd = tmp_path / "ascii.pcd"
    o3d.io.write_point_cloud(
        str(ascii_pcd), _o3d_cloud(o3d, rng.normal(size=(1000, 3))), write_ascii=True
    )
    data = ascii_pcd.read_bytes()
    (tmp_path / "cut_ascii.pcd").write_bytes(data[: len(data) // 2])
    # open3d itself returns 1000 points here, half of them uninitialised memory
    assert _error(tmp_path / "cut_ascii.pcd").startswith("truncated PCD file")
    compressed = tmp_path / "compressed.pcd"
    o3d.io.write_point_cloud(
        str(compressed), _o3d_cloud(o3d, rng.normal(size=(1000, 3))), compressed=True
    )
    data = compressed.read_bytes()
    (tmp_path / "cut_compressed.pcd").write_bytes(data[: len(data) // 2])
    assert _error(tmp_path / "cut_compressed.pcd").startswith("could not read PCD data")
    (tmp_path / "garbage.pcd").write_bytes(b"\x00\x01garbage\xff" * 100)
    assert _error(tmp_path / "garbage.pcd") == "not a PCD file (bad header)"
    (tmp_path / "text.pcd").write_text("1 2 3\n4 5 6\n")
    assert _error(tmp_path / "text.pcd") == "not a PCD file (bad header)"
    head = "VERSION 0.7\nFIELDS {f}\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
    head += "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n"
    (tmp_path / "abc.pcd").write_text(head.format(f="a b c", n=1) + "1 2 3\n")
    assert _error(tmp_path / "abc.pcd") == "PCD lacks x, y, z fields (has a, b, c)"
    (tmp_path / "zero.pcd").write_text(head.format(f="x y z", n=0))
    assert _error(tmp_path / "zero.pcd") == "empty point cloud (0 points)"
    assert _error(tmp_path / "missing.pcd") == "no such file"
    assert capfd.readouterr().out == ""  # open3d printed nothing on stdout


def test_xyz_family(tmp_path, o3d):
    (tmp_path / "c.xyz").write_text("1 2 3\n4 5 6\n\nnan 1 1\n")
    cloud = read_point_cloud(tmp_path / "c.xyz")
    assert np.array_equal(cloud.points, [[1, 2, 3], [4, 5, 6]])
    assert cloud.num_nonfinite_dropped == 1
    (tmp_path / "c.xyzn").write_text("1 2 3 0 0 1\n4 5 6 0 0 1\n")
    assert np.array_equal(read_point_cloud(tmp_path / "c.xyzn").points, [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "c.xyzrgb").write_text("1 2 3 0.5 0.5 0.5\n")
    assert np.array_equal(read_point_cloud(tmp_path / "c.xyzrgb").points, [[1, 2, 3]])
    (tmp_path / "c.txt").write_text("1 2 3\n")
    assert np.array_equal(read_point_cloud(tmp_path / "c.txt", fmt="xyz").points, [[1, 2, 3]])
    written = tmp_path / "o3d.xyz"
    o3d.io.write_point_cloud(str(written), _o3d_cloud(o3d, np.eye(3)))
    assert np.allclose(read_point_cloud(written).points, np.eye(3))


def test_pts_with_and_without_count_line(tmp_path, o3d):
    (tmp_path / "head.pts").write_text("3\n1 2 3 10 200 200 200\n4 5 6 10 0 0 0\n7 8 9 1 1 1 1\n")
    assert read_point_cloud(tmp_path / "head.pts").points.tolist() == [
        [1, 2, 3],
        [4, 5, 6],
        [7, 8, 9],
    ]
    # no count line: open3d's PTS reader would take '1' (first number) as the count
    (tmp_path / "bare.pts").write_text("1 2 3 100\n4 5 6 100\n")
    assert read_point_cloud(tmp_path / "bare.pts").points.tolist() == [[1, 2, 3], [4, 5, 6]]
    written = tmp_path / "o3d.pts"
    o3d.io.write_point_cloud(str(written), _o3d_cloud(o3d, np.eye(3) + 1))
    assert np.allclose(read_point_cloud(written).points, np.eye(3) + 1)
    # a short file: open3d pads the missing points with zeros
    (tmp_path / "short.pts").write_text("10\n1 2 3\n4 5 6\n")
    assert _error(tmp_path / "short.pts") == "PTS header says 10 points, the file holds 2"
    (tmp_path / "zero.pts").write_text("0\n")
    assert _error(tmp_path / "zero.pts") == "empty point cloud (0 points)"


def test_xyz_errors(tmp_path, o3d, capfd):
    (tmp_path / "words.xyz").write_text("hello world\nthis is not a cloud\n")
    assert _error(tmp_path / "words.xyz") == "no points found (expected lines of 'x y z')"
    (tmp_path / "csv.xyz").write_text("1,2,3\n4,5,6\n")
    assert _error(tmp_path / "csv.xyz").startswith("no points found")
    (tmp_path / "three.xyzn").write_text("1 2 3\n")
    assert _error(tmp_path / "three.xyzn") == "no points found (expected lines of 'x y z nx ny nz')"
    (tmp_path / "nan.xyz").write_text("nan 1 2\n1 inf 2\n")
    assert _error(tmp_path / "nan.xyz").startswith("no finite points (all 2 points")
    assert capfd.readouterr().out == ""


# ---------------------------------------------------------------- units


def test_check_units():
    metres = np.array([[0.0, 0, 0], [3.0, 1.0, 999.0]])
    check_units(metres, "a.ply")  # no error
    check_units(np.zeros((0, 3)), "a.ply")
    millimetres = np.array([[0.0, 0, 0], [4211.3, 120.0, 800.0]])
    with pytest.raises(InputError) as info:
        check_units(millimetres, "scan.ply")
    assert str(info.value) == (
        "scan.ply: extent 4211.3 along the largest axis looks like millimetres; "
        "pass --scale 0.001 (or --scale 1 to keep the units)"
    )
    check_units(millimetres, "scan.ply", max_extent=5000.0)
    with pytest.raises(ShapeError):
        check_units(np.zeros((3, 2)), "a.ply")


# ---------------------------------------------------------------- real data


def test_real_demo_pair(shared_data, o3d):
    path = shared_data / "pairs" / "3dmatch_demo" / "source.ply"
    cloud = read_point_cloud(path)
    assert cloud.points.shape == (15953, 3) and cloud.num_nonfinite_dropped == 0
    expected = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    assert np.array_equal(cloud.points, expected)
    check_units(cloud.points, path)


def test_real_3dmatch_fragment(shared_data, o3d):
    path = (
        shared_data / "3dmatch" / "sample" / "3DMatch" / "7-scenes-redkitchen" / "cloud_bin_0.ply"
    )
    cloud = read_point_cloud(path)
    assert cloud.points.shape == (258342, 3)
    extent = cloud.points.max(0) - cloud.points.min(0)
    assert np.all((extent > 1.0) & (extent < 5.0))  # a kitchen fragment, in metres
    expected = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    assert np.array_equal(cloud.points, expected)
    check_units(cloud.points, path)


# ---------------------------------------------------------------- 10M points


_MEASURE = """
import json, sys, time
from byoc_cli.io import read_point_cloud

def hwm_kb():  # peak RSS of this process (ru_maxrss would carry the parent's over exec)
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))

base = hwm_kb()
t = time.perf_counter()
cloud = read_point_cloud(sys.argv[1])
elapsed = time.perf_counter() - t
print(json.dumps({"n": len(cloud.points), "s": elapsed, "base_kb": base, "peak_kb": hwm_kb()}))
"""


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux /proc")
def test_ten_million_points_memory_and_time(tmp_path):
    # Measured on the 2-core dev box (float32 binary PLY, 120 MB, page cache warm), in a
    # fresh interpreter (34 MB baseline VmHWM after importing byoc_cli.io):
    #   10M points: 0.30-0.48 s, peak RSS +241 MB; with one NaN point: 0.47-0.85 s, +265 MB
    #   (the (N, 3) float64 result is 229 MB; NaN rows are compacted in place).
    #   float64 PLY (240 MB): 0.33-0.55 s, +253 MB. open3d's PLY reader: 0.97 s, +458 MB.
    n = 10_000_000
    rng = np.random.default_rng(1)
    points = rng.random((n, 3), dtype=np.float32).astype(np.float64)
    points[123] = np.nan
    path = tmp_path / "big.ply"
    write_ply(path, points)
    del points
    out = subprocess.run(
        [sys.executable, "-c", _MEASURE, str(path)], check=True, capture_output=True, text=True
    )
    result = json.loads(out.stdout)
    growth_mb = (result["peak_kb"] - result["base_kb"]) / 1024
    assert result["n"] == n - 1
    assert growth_mb < 350, f"peak RSS grew by {growth_mb:.0f} MB"
    assert result["s"] < 10, f"took {result['s']:.1f} s"


def test_npy_header_that_breaks_numpys_parser(tmp_path):
    """Found by the slow fuzz run: a NUL for the brace made numpy raise TokenError."""
    buffer = io.BytesIO()
    np.save(buffer, np.zeros((4, 3)))
    path = tmp_path / "brace.npy"
    path.write_bytes(buffer.getvalue().replace(b"{", b"\x00", 1))
    assert _error(path) == "not an NPY file (bad header)"
