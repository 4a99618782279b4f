"""``--aligned``: the moved source in the format its name asks for; a LAS output needs a LAS
source (its header and records are copied)."""

from __future__ import annotations

import laspy
import numpy as np
import pytest
from plyfile import PlyData

from byoc_cli.errors import InputError
from byoc_cli.io.aligned import aligned_format, write_aligned
from byoc_cli.io.e57 import read_e57_points


@pytest.mark.parametrize(
    ("output", "source", "fmt"),
    [
        ("m.las", "s.las", "las"),
        ("m.LAZ", "s.laz", "las"),
        ("m.las", "s.LAZ", "las"),
        ("m.e57", "s.ply", "e57"),
        ("m.e57", "site.e57:1", "e57"),
        ("m.ply", "s.las", "ply"),
        ("m.xyz", "s.las", "ply"),
    ],
)
def test_the_output_name_picks_the_format(output, source, fmt):
    assert aligned_format(output, source) == fmt


@pytest.mark.parametrize("source", ["s.ply", "site.e57:1", "d.png"])
def test_a_las_output_needs_a_las_source(source):
    with pytest.raises(InputError, match="copies the header and point records of a LAS/LAZ"):
        aligned_format("m.las", source)


def test_each_format_is_written(tmp_path):
    points = np.random.default_rng(0).uniform(0, 1, (50, 3)) + np.array([4.5e5, 5.2e6, 10.0])
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = np.full(3, 1e-4), np.array([4.5e5, 5.2e6, 0.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = points.T
    las.write(str(tmp_path / "s.las"))
    moved = points + np.array([1.0, 2.0, 3.0])
    write_aligned(tmp_path / "m.las", moved, tmp_path / "s.las")
    write_aligned(tmp_path / "m.e57", moved, tmp_path / "s.las")
    write_aligned(tmp_path / "m.ply", moved, tmp_path / "s.las")
    assert np.abs(laspy.read(str(tmp_path / "m.las")).xyz - moved).max() <= 5e-5 + 1e-9
    assert np.abs(read_e57_points(tmp_path / "m.e57") - moved).max() < 1e-6
    vertex = PlyData.read(str(tmp_path / "m.ply"))["vertex"]
    assert vertex["x"].dtype == np.float64
    np.testing.assert_array_equal(np.column_stack([vertex[k] for k in "xyz"]), moved)
