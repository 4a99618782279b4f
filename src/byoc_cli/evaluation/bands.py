"""Overlap bands of a fragment benchmark: 3DMatch's pairs (overlap above 30 %) and 3DLoMatch's
(10 to 30 %, Huang et al., Predator, CVPR 2021) in one run (``byoc eval-fmr --overlap-bands``).

A band ``(low, high]`` holds the pairs with ``low < overlap <= high``, the overlap read from
``gt_overlap.log`` (``byoc make-fragments`` writes it; the official 3DLoMatch ground truth has
it); the same convention as ``make-fragments --min-overlap / --max-overlap``.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import NamedTuple

__all__ = ["OverlapBand", "parse_overlap_bands", "split_by_band"]


class OverlapBand(NamedTuple):
    """The pairs with ``low < overlap <= high``.

    Attributes:
        low, high: the band's edges, fractions in ``[0, 1]``.
    """

    low: float
    high: float

    @property
    def label(self) -> str:
        """``10-30%`` (or ``>30%`` when the band ends at 1), the table's column suffix."""
        if self.high >= 1.0:
            return f">{100 * self.low:g}%"
        return f"{100 * self.low:g}-{100 * self.high:g}%"

    def holds(self, overlap: float) -> bool:
        """True when ``low < overlap <= high``."""
        return self.low < overlap <= self.high


def parse_overlap_bands(text: str) -> list[OverlapBand]:
    """Bands from increasing edges: ``"0.1,0.3,1"`` -> ``(0.1, 0.3], (0.3, 1]``.

    Args:
        text: at least two comma- or space-separated numbers in ``[0, 1]``, strictly
            increasing.

    Returns:
        One :class:`OverlapBand` per consecutive pair of edges, lowest first.

    Raises:
        ValueError: fewer than two edges, a non-number, an edge outside ``[0, 1]`` or edges
            not strictly increasing.
    """
    parts = text.replace(",", " ").split()
    try:
        edges = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"{text!r}: edges must be numbers, e.g. 0.1,0.3,1") from None
    if len(edges) < 2:
        raise ValueError(f"{text!r}: give at least two edges, e.g. 0.1,0.3,1")
    if not all(0.0 <= e <= 1.0 for e in edges):
        raise ValueError(f"{text!r}: edges are overlaps, in [0, 1]")
    if any(b <= a for a, b in itertools.pairwise(edges)):
        raise ValueError(f"{text!r}: edges must increase strictly")
    return [OverlapBand(a, b) for a, b in itertools.pairwise(edges)]


def split_by_band(
    overlaps: Sequence[float], bands: Sequence[OverlapBand]
) -> tuple[list[list[int]], list[int]]:
    """Which pairs fall in which band.

    Args:
        overlaps: ``(P,)`` the overlap of each pair.
        bands: from :func:`parse_overlap_bands` (edges increasing, so a pair is in one band
            at most).

    Returns:
        ``(members, outside)``: ``members[b]`` the indices of the pairs in ``bands[b]``, in
        order; ``outside`` the indices of the pairs in no band.
    """
    members: list[list[int]] = [[] for _ in bands]
    outside: list[int] = []
    for k, overlap in enumerate(overlaps):
        band = next((b for b, band in enumerate(bands) if band.holds(overlap)), None)
        if band is None:
            outside.append(k)
        else:
            members[band].append(k)
    return members, outside
