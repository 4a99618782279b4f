import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.geometry import voxelize
from byoc_cli.geometry.voxel import near_occupied


def test_first_point_per_voxel_hand_example():
    points = torch.tensor(
        [
            [0.01, 0.01, 0.01],
            [0.30, 0.0, 0.0],
            [0.02, 0.03, 0.04],
            [-0.01, 0.0, 0.0],
            [0.31, 0.0, 0.0],
        ]
    )
    grid = voxelize(points, 0.1)
    # voxels in order of first point: (0,0,0) <- 0, (3,0,0) <- 1, (-1,0,0) <- 3
    assert grid.point_index.tolist() == [0, 1, 3]
    assert grid.coords.tolist() == [[0, 0, 0], [3, 0, 0], [-1, 0, 0]]
    assert grid.voxel_of_point.tolist() == [0, 1, 0, 2, 1]


@settings(max_examples=30, deadline=None)
@given(n=st.integers(0, 300), seed=st.integers(0, 2**31 - 1), size=st.floats(0.01, 1.0))
def test_strict_voxel_point_map(n, seed, size):
    g = torch.Generator().manual_seed(seed)
    points = torch.randn(n, 3, generator=g)
    grid = voxelize(points, size)
    m = grid.point_index.shape[0]
    assert torch.equal(grid.voxel_of_point[grid.point_index], torch.arange(m))
    # every point lies in its voxel and the kept point is the first one there
    expected_coords = torch.floor(points.double() / size).long()
    assert torch.equal(expected_coords, grid.coords[grid.voxel_of_point])
    for v in range(m):
        members = (grid.voxel_of_point == v).nonzero().flatten()
        assert members.min().item() == grid.point_index[v].item()
    assert torch.all(grid.point_index[1:] > grid.point_index[:-1])
    assert len({tuple(c) for c in grid.coords.tolist()}) == m


def test_bad_arguments():
    with pytest.raises(ShapeError):
        voxelize(torch.zeros(4, 2), 0.1)
    with pytest.raises(ShapeError, match="voxel_size"):
        voxelize(torch.zeros(4, 3), 0.0)
    with pytest.raises(ShapeError, match="out of range"):
        voxelize(torch.tensor([[1e6, 0.0, 0.0]]), 0.01)


def test_near_occupied_against_brute_force():
    g = torch.Generator().manual_seed(1)
    ref = torch.rand(500, 3, generator=g, dtype=torch.float64)
    query = torch.rand(400, 3, generator=g, dtype=torch.float64) * 1.5
    cell = 0.05
    hit = near_occupied(query, ref, cell)
    dist = torch.cdist(query, ref).min(dim=1).values
    assert torch.all(hit[dist < cell])  # everything within one cell is found
    assert torch.all(dist[hit] < 2 * 3**0.5 * cell)  # nothing farther than the 3x3x3 block
    assert near_occupied(query[:0], ref, cell).shape == (0,)
