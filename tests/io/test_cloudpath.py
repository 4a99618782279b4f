"""Cloud names: ``site.e57:2`` is scan 2 of ``site.e57``; every other name is a file."""

from __future__ import annotations

from pathlib import Path

import pytest

from byoc_cli.io.cloudpath import CloudPath, cloud_file, cloud_stem, parse_cloud_path, scan_path


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("site.e57:2", CloudPath(Path("site.e57"), 2)),
        ("dir/Site.E57:0", CloudPath(Path("dir/Site.E57"), 0)),
        ("site.e57", CloudPath(Path("site.e57"), None)),
        ("site.ply:2", CloudPath(Path("site.ply:2"), None)),  # only E57 files hold scans
        ("site.e57:x", CloudPath(Path("site.e57:x"), None)),
        ("site.e57:-1", CloudPath(Path("site.e57:-1"), None)),
        ("scan#1.ply", CloudPath(Path("scan#1.ply"), None)),
    ],
)
def test_a_scan_index_follows_the_e57_file_after_a_colon(name, expected):
    assert parse_cloud_path(name) == expected


def test_an_existing_file_of_that_name_is_read_as_itself(tmp_path):
    odd = tmp_path / "odd.e57:3"
    odd.write_bytes(b"")
    assert parse_cloud_path(odd) == CloudPath(odd, None)
    assert parse_cloud_path(tmp_path / "odd.e57:4") == CloudPath(tmp_path / "odd.e57", 4)


def test_stems_name_each_scan_and_files_name_the_file():
    assert cloud_stem("a/site.e57:2") == "site_scan2"
    assert cloud_stem("a/site.e57") == "site"
    assert cloud_stem(Path("a/b.ply")) == "b"
    assert cloud_file("a/site.e57:2") == Path("a/site.e57")
    assert scan_path(Path("a/site.e57"), 7) == Path("a/site.e57:7")
    assert parse_cloud_path(scan_path("x.e57", 5)) == CloudPath(Path("x.e57"), 5)
