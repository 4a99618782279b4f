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
