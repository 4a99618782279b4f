"""PLY headers whose counts the file cannot hold are refused before anything is allocated."""

from __future__ import annotations

import pytest

from byoc_cli.errors import InputError
from byoc_cli.io import read_point_cloud

XYZ = "property float x\nproperty float y\nproperty float z\n"


@pytest.mark.parametrize("fmt", ["ascii 1.0", "binary_little_endian 1.0"])
def test_huge_counts_before_the_vertices_are_refused(tmp_path, fmt):
    path = tmp_path / "faces_first.ply"
    header = f"ply\nformat {fmt}\nelement face 1000000000000\n"
    header += "property list uchar int vertex_indices\nelement vertex 3\n" + XYZ + "end_header\n"
    path.write_bytes(header.encode() + b"0 0 0\n" * 4)
    with pytest.raises(InputError, match=r"^.*faces_first\.ply: truncated PLY file"):
        read_point_cloud(path)


def test_huge_ascii_vertex_count_names_the_file(tmp_path):
    path = tmp_path / "big.ply"
    path.write_text(
        f"ply\nformat ascii 1.0\nelement vertex 1000000000000\n{XYZ}end_header\n1 2 3\n"
    )
    with pytest.raises(InputError, match="header says 1000000000000 vertices, found 1") as info:
        read_point_cloud(path)
    assert info.value.path == str(path)


def test_scalars_are_float_properties_after_the_colours(tmp_path):
    import numpy as np
    from plyfile import PlyData

    from byoc_cli.errors import ShapeError
    from byoc_cli.io import write_ply

    points = np.arange(12, dtype=np.float64).reshape(4, 3)
    colors = np.full((4, 3), 7, dtype=np.uint8)
    write_ply(tmp_path / "s.ply", points, colors, scalars={"residual": np.array([0, 1, 2, 3.5])})
    vertex = PlyData.read(str(tmp_path / "s.ply"))["vertex"]
    names = [p.name for p in vertex.properties]
    assert names == ["x", "y", "z", "red", "green", "blue", "residual"]
    assert vertex["residual"].dtype == np.float32
    np.testing.assert_array_equal(vertex["residual"], [0, 1, 2, 3.5])
    for bad in ({"residual": np.zeros(3)}, {"red": np.zeros(4)}, {"a b": np.zeros(4)}):
        with pytest.raises(ShapeError):
            write_ply(tmp_path / "bad.ply", points, colors, scalars=bad)
    assert not (tmp_path / "bad.ply").exists()
