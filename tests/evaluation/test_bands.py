"""Overlap bands of eval-fmr: parsing the edges, which pair falls in which band."""

from __future__ import annotations

import pytest

from byoc_cli.evaluation.bands import OverlapBand, parse_overlap_bands, split_by_band


def test_edges_make_consecutive_bands_with_labels():
    bands = parse_overlap_bands("0.1,0.3,1")
    assert bands == [OverlapBand(0.1, 0.3), OverlapBand(0.3, 1.0)]
    assert [b.label for b in bands] == ["10-30%", ">30%"]
    assert parse_overlap_bands("0 0.5") == [OverlapBand(0.0, 0.5)]


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("0.3", "at least two edges"),
        ("", "at least two edges"),
        ("0.1,x", "numbers"),
        ("0.1,1.5", "in [0, 1]"),
        ("-0.1,0.3", "in [0, 1]"),
        ("0.3,0.1", "increase strictly"),
        ("0.1,0.1,0.3", "increase strictly"),
    ],
)
def test_bad_edges_are_refused(text, problem):
    with pytest.raises(
        ValueError, match="^'.*': .*" + problem.replace("[", r"\[").replace("]", r"\]")
    ):
        parse_overlap_bands(text)


def test_a_band_is_open_below_and_closed_above():
    """(low, high]: 0.3 belongs to 10-30 % (as make-fragments --max-overlap 0.3 keeps it), 0.1
    to no band, like make-fragments --min-overlap 0.1 drops it."""
    bands = parse_overlap_bands("0.1,0.3,1")
    overlaps = [0.05, 0.1, 0.1001, 0.2, 0.3, 0.30001, 0.9, 1.0]
    members, outside = split_by_band(overlaps, bands)
    assert members == [[2, 3, 4], [5, 6, 7]]
    assert outside == [0, 1]
    assert split_by_band([], bands) == ([[], []], [])
