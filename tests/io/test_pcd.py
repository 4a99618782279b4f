"""PCD headers are checked against the spec before open3d reads (it crashed or asked for
terabytes on headers that lie; found by tests/cli/test_fuzz_readers.py)."""

from __future__ import annotations

import numpy as np
import pytest

from byoc_cli.errors import InputError
from byoc_cli.io import read_point_cloud

POINTS = np.arange(12, dtype="<f4").reshape(4, 3)


def _pcd(tmp_path, **fields) -> object:
    header = {
        "VERSION": "0.7",
        "FIELDS": "x y z",
        "SIZE": "4 4 4",
        "TYPE": "F F F",
        "COUNT": "1 1 1",
        "WIDTH": "4",
        "HEIGHT": "1",
        "POINTS": "4",
        "DATA": "binary",
    }
    header.update(fields)
    path = tmp_path / "c.pcd"
    text = "".join(f"{key} {value}\n" for key, value in header.items())
    path.write_bytes(text.encode() + POINTS.tobytes())
    return path


def test_valid_binary_pcd(tmp_path):
    assert np.array_equal(read_point_cloud(_pcd(tmp_path)).points, POINTS)


@pytest.mark.parametrize(
    ("fields", "phrase"),
    [
        ({"COUNT": "1 1 -7511898015084", "POINTS": "4642223007632"}, "out of range"),
        ({"POINTS": "5"}, "is not WIDTH x HEIGHT"),
        ({"SIZE": "4 4 3"}, "SIZE must be"),
        ({"TYPE": "F F Q"}, "TYPE F, I or U"),
        ({"SIZE": "4 4"}, "differ in length"),
        ({"WIDTH": "-4", "HEIGHT": "-1"}, "out of range"),
        ({"DATA": "binary_compressed"}, "could not read PCD data"),
    ],
)
def test_lying_headers_are_refused(tmp_path, fields, phrase):
    with pytest.raises(InputError, match=phrase) as info:
        read_point_cloud(_pcd(tmp_path, **fields))
    assert info.value.path.endswith("c.pcd")
