"""Voxel-grid neighbourhoods: averages, neighbour cells, nearest points."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.geometry.neighbors import (
    CELL_LIMIT,
    DENSE_CELLS,
    MAX_PER_CELL,
    CellIndex,
    DenseCells,
    Nearest,
    _distance2,
    candidate_coordinates,
    cell_keys,
    nearest_candidates,
    nearest_of,
    neighbor_positions,
    smallest,
    voxel_average,
    voxel_means,
)


def _cloud(n: int, seed: int, scale: float = 0.3) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 2 * scale


def test_voxel_average_hand_case():
    pts = torch.tensor(
        [[0.01, 0.01, 0.01], [0.03, 0.05, 0.07], [0.15, 0.0, 0.0], [-0.05, 0.0, 0.0]],
        dtype=torch.float64,
    )
    out = voxel_average(pts, 0.1)
    expected = {(0.02, 0.03, 0.04), (0.15, 0.0, 0.0), (-0.05, 0.0, 0.0)}
    assert {tuple(round(v, 9) for v in p) for p in out.tolist()} == expected


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), size=st.sampled_from([0.02, 0.05, 0.2]))
def test_voxel_means_weighted_by_counts_are_the_means_of_the_points(seed, size):
    # a finer level's averages weighted by their counts: each coarse cell's average is the
    # mean of the points whose fine average falls in it
    pts = _cloud(800, seed)
    fine, counts = voxel_means(pts, size / 4)
    assert torch.equal(fine, voxel_average(pts, size / 4)) and int(counts.sum()) == len(pts)
    coarse, weights = voxel_means(fine, size, counts)
    assert int(weights.sum()) == len(pts)
    owner = {}
    fine_of = {tuple(math.floor(v / (size / 4)) for v in p): p for p in fine.tolist()}
    for p in pts.tolist():
        f = fine_of[tuple(math.floor(v / (size / 4)) for v in p)]
        owner.setdefault(tuple(math.floor(v / size) for v in f), []).append(p)
    assert len(coarse) == len(owner)
    for p, w in zip(coarse.tolist(), weights.tolist(), strict=True):
        group = owner[tuple(math.floor(v / size) for v in p)]
        assert w == len(group) and np.allclose(p, np.mean(group, axis=0), atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), size=st.sampled_from([0.01, 0.05, 0.2]))
def test_voxel_average_is_the_mean_of_each_cell(seed, size):
    pts = _cloud(500, seed)
    out = voxel_average(pts, size)
    cells = {}
    for p in pts.tolist():
        cells.setdefault(tuple(math.floor(v / size) for v in p), []).append(p)
    assert len(out) == len(cells)
    means = {k: np.mean(v, axis=0) for k, v in cells.items()}
    for p in out.tolist():
        key = tuple(math.floor(v / size) for v in p)
        assert np.allclose(p, means[key], atol=1e-12)


def test_cell_keys_order_and_limit():
    cells = torch.tensor([[0, 0, 0], [0, 0, 1], [0, 1, -5], [1, -9, 0], [-1, 3, 3]])
    keys = cell_keys(cells)
    assert torch.equal(torch.argsort(keys), torch.tensor([4, 0, 1, 2, 3]))
    assert int(keys[1] - keys[0]) == 1  # neighbours along z: consecutive keys
    with pytest.raises(ValueError, match="cells"):
        cell_keys(torch.tensor([[CELL_LIMIT, 0, 0]]))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_neighbor_positions_match_a_dictionary(seed):
    g = torch.Generator().manual_seed(seed)
    occupied = torch.unique(cell_keys(torch.randint(-4, 5, (300, 3), generator=g)))
    queries = torch.randint(-5, 6, (60, 3), generator=g)
    pos = neighbor_positions(occupied, queries)
    where = {int(k): i for i, k in enumerate(occupied.tolist())}
    for q, row in zip(queries.tolist(), pos.tolist(), strict=True):
        expected = set()
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    key = int(cell_keys(torch.tensor([[q[0] + dx, q[1] + dy, q[2] + dz]]))[0])
                    if key in where:
                        expected.add(where[key])
        assert {p for p in row if p >= 0} == expected
        assert len([p for p in row if p >= 0]) == len(expected)  # no cell twice


@pytest.mark.parametrize("reach", [1, 2])
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_neighbor_positions_reach_matches_a_dictionary(reach, seed):
    g = torch.Generator().manual_seed(seed)
    occupied = torch.unique(cell_keys(torch.randint(-3, 4, (80, 3), generator=g)))
    queries = torch.randint(-6, 7, (30, 3), generator=g)
    pos = neighbor_positions(occupied, queries, reach)
    where = {int(k): i for i, k in enumerate(occupied.tolist())}
    span = range(-reach, reach + 1)
    for q, row in zip(queries.tolist(), pos.tolist(), strict=True):
        # in the order of the offsets (dx, dy, dz), dz fastest
        expected = [
            where.get(int(cell_keys(torch.tensor([[q[0] + dx, q[1] + dy, q[2] + dz]]))[0]), -1)
            for dx in span
            for dy in span
            for dz in span
        ]
        assert row == expected


def test_neighbor_positions_refuse_cells_past_the_limit():
    with pytest.raises(ValueError, match="cells"):
        neighbor_positions(torch.tensor([0]), torch.tensor([[CELL_LIMIT - 1, 0, 0]]), reach=1)


@pytest.mark.parametrize("reach", [1, 2])
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_dense_cells_give_what_the_sorted_keys_give(reach, seed):
    g = torch.Generator().manual_seed(seed)
    cells = torch.randint(-5, 6, (120, 3), generator=g)
    keys, first = torch.unique(cell_keys(cells), return_inverse=True)
    distinct = torch.zeros(len(keys), 3, dtype=torch.int64).index_copy_(0, first, cells)
    dense = DenseCells.build(distinct, torch.arange(len(keys)), reach=2)
    queries = torch.randint(-12, 13, (200, 3), generator=g)  # many far outside the box
    assert torch.equal(dense.lookup(queries, reach), neighbor_positions(keys, queries, reach))


def test_dense_cells_only_within_the_budget_and_the_padding():
    far = torch.tensor([[0, 0, 0], [DENSE_CELLS, 0, 0]])
    assert DenseCells.build(far, torch.arange(2), reach=1) is None
    dense = DenseCells.build(torch.zeros(1, 3, dtype=torch.int64), torch.zeros(1), reach=1)
    with pytest.raises(ValueError, match="reach"):
        dense.lookup(torch.zeros(1, 3, dtype=torch.int64), reach=2)


@pytest.mark.parametrize("averaged", [True, False])
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_a_dense_cell_index_finds_the_same_points(averaged, seed):
    size = 0.05
    target = _cloud(1500, seed)
    if averaged:
        target = voxel_average(target, size)
    plain, dense = CellIndex(target, size), CellIndex(target, size, dense_reach=2)
    assert plain.dense is None and dense.dense is not None
    queries = _cloud(300, seed + 1, scale=0.45)
    for reach in (1, 2):
        assert torch.equal(plain.around(queries, reach), dense.around(queries, reach))
        assert torch.equal(
            nearest_candidates(plain, queries, 8, reach),
            nearest_candidates(dense, queries, 8, reach),
        )


def test_neighbor_positions_of_nothing():
    assert neighbor_positions(
        torch.zeros(0, dtype=torch.int64), torch.zeros(3, 3).long()
    ).shape == (
        3,
        27,
    )
    assert (
        neighbor_positions(torch.zeros(0, dtype=torch.int64), torch.zeros(3, 3).long()) == -1
    ).all()


@pytest.mark.parametrize("averaged", [True, False])
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_around_holds_every_point_within_a_cell_and_nearest_is_exact(averaged, seed):
    size = 0.05
    target = _cloud(3000, seed)
    if averaged:  # one point per cell: the refinement's targets
        target = voxel_average(target, size)
    index = CellIndex(target, size)
    # both ways of reading the cells: one point per cell, and several
    assert index.max_count == 1 if averaged else index.max_count > 1
    queries = _cloud(200, seed + 1, scale=0.32)
    cand = index.around(queries)
    d = torch.cdist(queries, target)
    for i in range(len(queries)):
        within = set(torch.nonzero(d[i] < size).flatten().tolist())
        assert within <= {c for c in cand[i].tolist() if c >= 0}
    near = nearest_of(index, queries, nearest_candidates(index, queries, 8))
    best, arg = d.min(dim=1)
    close = best < size
    assert torch.equal(near.index[close], arg[close])
    assert torch.allclose(near.distance2[close].double(), best[close] ** 2, atol=1e-7)


@pytest.mark.parametrize("seed", [0, 1])
def test_nearest_of_moved_queries_with_their_candidates_coordinates_is_the_same(seed):
    index = CellIndex(voxel_average(_cloud(3000, seed), 0.05), 0.05)
    queries = _cloud(300, seed + 1, scale=0.32)
    candidates = nearest_candidates(index, queries, 8)
    candidates[::7, 3:] = -1  # fewer candidates for some
    coordinates = candidate_coordinates(index, candidates)
    for shift in (0.0, 0.004, -0.01):  # queries that moved less than a cell since the search
        moved = queries + shift
        alone, given = (
            nearest_of(index, moved, candidates),
            _distance2_nearest(index, moved, candidates),
        )
        again = nearest_of(index, moved, candidates, coordinates)
        for got in (alone, again):
            assert torch.equal(got.index, given.index)
            assert got.distance2.numpy().tobytes() == given.distance2.numpy().tobytes()


def _distance2_nearest(index, queries, candidates):
    """nearest_of as it was written before the coordinates could be given."""
    safe = torch.where(candidates < 0, index.none, candidates)
    best, pick = _distance2(index, safe, queries).min(dim=1)
    return Nearest(candidates.gather(1, pick[:, None])[:, 0], best)


def test_nearest_of_with_no_candidates():
    pts = _cloud(10, 0)
    out = nearest_of(CellIndex(pts, 0.1), pts[:2], torch.full((2, 4), -1, dtype=torch.int64))
    assert torch.isinf(out.distance2).all()


def test_a_cell_index_refuses_a_cell_fuller_than_its_bound():
    # the scattered points stay out of the full cell at the origin
    g = torch.Generator().manual_seed(0)
    scattered = 0.5 + torch.rand(100, 3, dtype=torch.float64, generator=g)
    pts = torch.cat([torch.zeros(MAX_PER_CELL + 1, 3, dtype=torch.float64), scattered])
    with pytest.raises(ValueError, match="k-d tree"):
        CellIndex(pts.double(), 0.1)
    assert CellIndex(pts.double(), 0.1, max_per_cell=None).max_count == MAX_PER_CELL + 1


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, 40),
    st.sampled_from([1, 2, 8, 27]),
    st.integers(1, 30),
    st.integers(0, 10_000),
    st.booleans(),
)
def test_smallest_is_topk_up_to_the_order_of_equal_values(rows, k, extra, seed, coarse):
    """Values as torch.topk's (ascending), and the same columns where a row's values differ;
    rows of infinities (cells with no point) and ties (coarse values) included."""
    g = torch.Generator().manual_seed(seed)
    values = torch.rand(rows, k + extra - 1, generator=g)
    if coarse:
        values = (values * 4).floor()  # many ties
    values[values > (2.5 if coarse else 0.7)] = float("inf")
    got_values, got_columns = smallest(values, k)
    want_values, want_columns = torch.topk(values, k, dim=1, largest=False)
    assert torch.equal(got_values, want_values)
    assert got_columns.dtype == torch.int64 and got_columns.shape == (rows, k)
    assert torch.equal(values.gather(1, got_columns), got_values)
    if not coarse and rows:
        finite = torch.isfinite(want_values)
        assert torch.equal(got_columns[finite], want_columns[finite])
