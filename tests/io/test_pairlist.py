"""Pair lists of register-batch: columns, comments, relative paths, shards."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from byoc_cli.errors import InputError
from byoc_cli.io.pairlist import PairEntry, default_output_name, read_pair_list, shard


def test_columns_comments_and_relative_paths(tmp_path: Path):
    listing = tmp_path / "sub" / "pairs.txt"
    listing.parent.mkdir()
    listing.write_text("# header\n\na.ply  b.ply\n/abs/c.ply d.ply out/T.txt  # note\n")
    pairs = read_pair_list(listing)
    assert pairs == [
        PairEntry(0, 3, listing.parent / "a.ply", listing.parent / "b.ply", None),
        PairEntry(1, 4, Path("/abs/c.ply"), listing.parent / "d.ply", listing.parent / "out/T.txt"),
    ]
    assert default_output_name(Path("x/a.ply"), Path("b.npy")) == "a__b.txt"
    assert default_output_name(Path("s.e57:0"), Path("s.e57:1")) == "s_scan0__s_scan1.txt"


@pytest.mark.parametrize("text", ["a\n", "a b c d e\n", "# only\n", ""])
def test_malformed_lists_name_the_file(tmp_path: Path, text: str):
    listing = tmp_path / "p.txt"
    listing.write_text(text)
    with pytest.raises(InputError, match=r"p\.txt"):
        read_pair_list(listing)


def test_a_fourth_column_is_the_initial_pose_after_the_output(tmp_path: Path):
    listing = tmp_path / "pairs.txt"
    listing.write_text("a.ply b.ply T.txt poses/init.txt  # guess\nc.ply d.ply\n")
    with_init, without = read_pair_list(listing)
    assert with_init.output == tmp_path / "T.txt"
    assert with_init.init == tmp_path / "poses/init.txt"
    assert without.output is None and without.init is None


def test_an_init_column_needs_the_output_column_before_it(tmp_path: Path):
    listing = tmp_path / "pairs.txt"
    listing.write_text("a.ply b.ply T.txt init.txt extra\n")
    with pytest.raises(InputError, match=r"line 1: expected 'source target \[output \[init\]\]'"):
        read_pair_list(listing)
    listing.write_text("a.ply b.ply\na.ply b.ply same.txt same.txt\n")
    with pytest.raises(InputError, match="line 2: the init column names the output column's file"):
        read_pair_list(listing)


@given(st.integers(1, 40), st.integers(1, 7))
def test_shards_partition_the_list(n: int, count: int):
    pairs = [PairEntry(k, k + 1, Path(f"{k}a"), Path(f"{k}b"), None) for k in range(n)]
    parts = [shard(pairs, i, count) for i in range(count)]
    assert sorted(p.index for part in parts for p in part) == list(range(n))
    with pytest.raises(ValueError):
        shard(pairs, count, count)
