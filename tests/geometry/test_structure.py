"""A cloud's large planes, the fit of the rest and the turned alternatives
(geometry/structure.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.geometry.structure import (
    CORRELATION_CELLS,
    _correlation,
    clutter_fit,
    clutter_shares,
    correlation_shifts,
    structure,
    turned_alternatives,
)
from tests.pipeline._rooms import SEEN_TWICE, seen_twice, turn_z

VOXEL = 0.05
TRUTH = SEEN_TWICE


@pytest.fixture(scope="module")
def room():
    src, tgt = seen_twice()
    return structure(src, VOXEL), structure(tgt, VOXEL)


def test_the_walls_floor_and_ceiling_are_structure_and_the_boxes_are_not(room):
    _, tgt = room
    p, mask = tgt.points, tgt.mask
    on_shell = (np.abs(np.abs(p[:, :2]) - [1.5, 1.2]).min(axis=1) < 0.01) | (
        np.abs(p[:, 2] - 1.0) > 0.99
    )
    assert mask[on_shell].mean() > 0.75  # not where two planes meet: normals across the edge
    lifted = ~on_shell & (p[:, 2] > 0.05)  # the boxes' sides and tops
    assert mask[lifted].mean() < 0.2
    assert abs(tgt.directions[tgt.up][2]) > 0.99


def test_a_half_turn_fits_the_planes_but_not_the_boxes(room):
    src, tgt = room
    right = clutter_fit(src, tgt, TRUTH, 2 * VOXEL)
    turned = clutter_fit(src, tgt, turn_z(180.0) @ TRUTH, 2 * VOXEL)
    assert right.clutter > 0.95 and right.structure > 0.95
    assert turned.structure > 0.95  # the room's shell maps onto itself
    assert turned.clutter < 0.6


def test_one_turned_alternative_of_a_half_turn_is_the_truth(room):
    src, tgt = room
    alternatives = turned_alternatives(src, tgt, turn_z(180.0) @ TRUTH, VOXEL)
    assert len(alternatives) == 3
    for A in alternatives:
        assert np.allclose(A[:3, :3] @ A[:3, :3].T, np.eye(3), atol=1e-9)
    closest = min(alternatives, key=lambda A: np.abs(A - TRUTH).max())
    assert np.abs(closest - TRUTH).max() < 2 * VOXEL


def test_with_correlate_each_turn_also_starts_where_it_overlays_the_most(room):
    src, tgt = room
    alternatives = turned_alternatives(src, tgt, turn_z(180.0) @ TRUTH, VOXEL, correlate=True)
    assert len(alternatives) == 6
    for A in alternatives[3:]:
        assert np.allclose(A[:3, :3] @ A[:3, :3].T, np.eye(3), atol=1e-9)
    closest = min(alternatives[3:], key=lambda A: np.abs(A - TRUTH).max())
    assert np.abs(closest - TRUTH).max() < 4 * VOXEL  # within a cell of three voxels


def test_the_correlation_finds_a_known_shift_whatever_a_stray_point(room):
    _, tgt = room
    shift = np.array([0.45, -0.3, 0.15])  # whole cells of 0.15
    moved = tgt.points - shift
    (found,) = correlation_shifts([moved], tgt.points, 0.05)
    assert np.allclose(found, shift, atol=1e-9)
    strays = np.vstack([moved, [[1e6, 0.0, 0.0]], [[0.0, -1e30, 0.0]]])
    (again,) = correlation_shifts([strays], np.vstack([tgt.points, [[0, 0, 1e9]]]), 0.05)
    assert np.allclose(again, shift, atol=1e-9)


def test_the_correlation_grid_stays_bounded_on_a_wide_span():
    """A span of kilometres takes coarser cells, not more of them."""
    rng = np.random.default_rng(0)
    wide = rng.uniform(-2000.0, 2000.0, size=(5000, 3))
    (found,) = correlation_shifts([wide], wide, 0.01)
    cell = (4000.0**3 / CORRELATION_CELLS) ** (1 / 3)
    assert np.all(np.abs(found) <= cell)


def test_the_clutter_shares_are_the_clutter_fits(room):
    src, tgt = room
    transforms = [TRUTH, turn_z(180.0) @ TRUTH, turn_z(90.0) @ TRUTH]
    shares = clutter_shares(src, tgt, transforms, 2 * VOXEL)
    expected = [clutter_fit(src, tgt, T, 2 * VOXEL).clutter for T in transforms]
    assert np.allclose(shares, expected)


def test_bad_input_is_refused():
    with pytest.raises(ShapeError):
        structure(np.zeros((2, 3)), VOXEL)
    with pytest.raises(ShapeError):
        structure(np.zeros((10, 2)), VOXEL)
    with pytest.raises(ShapeError):
        structure(np.random.default_rng(0).random((10, 3)), 0.0)


@settings(max_examples=40, deadline=None)
@given(
    counts=st.lists(st.integers(0, 60), min_size=1, max_size=300),
    other=st.lists(st.integers(0, 60), min_size=1, max_size=300),
)
def test_the_plane_offsets_correlate_as_numpy_does(counts, other):
    """The FFT correlation of two offset histograms is numpy's direct one, to the count (the
    direct one is quadratic in the histograms' length, which a stray point far out makes
    long)."""
    size = max(len(counts), len(other))
    h = np.pad(np.array(counts), (0, size - len(counts)))
    g = np.pad(np.array(other), (0, size - len(other)))
    expected = np.correlate(h.astype(np.float64), g.astype(np.float64), mode="full")
    assert np.array_equal(_correlation(h, g), expected)
