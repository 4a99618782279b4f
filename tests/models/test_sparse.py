"""Sparse convolution against naive dense references computed here."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.models.sparse import (
    CoordinateManager,
    SparseBatchNorm,
    SparseReLU,
    SparseTensor,
    StridedConv,
    SubmanifoldConv,
    TransposedConv,
    kernel_offsets,
    sparse_cat,
    sparse_conv,
)
from byoc_cli.models.sparse import maps as sparse_module

F64 = torch.float64


@pytest.fixture(autouse=True)
def _one_thread():
    """One intra-op thread: these tensors are tiny, so parallel regions only add overhead,
    and on a busy machine every one of them can stall for a scheduler time slice."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def random_sites(generator, size=6, density=0.4, low=-3, batches=1):
    """Distinct ``(N, 4)`` sites in a ``size**3`` box starting at ``low``, per batch."""
    rows = []
    for b in range(batches):
        occupied = torch.rand(size, size, size, generator=generator) < density
        xyz = occupied.nonzero() + low
        rows.append(torch.cat([torch.full((xyz.shape[0], 1), b), xyz], dim=1))
    return torch.cat(rows)


def dense_grid(coords, feats, low, size):
    """``(1, C, size, size, size)`` grid holding ``feats`` at ``coords - low`` (batch 0)."""
    grid = feats.new_zeros(1, feats.shape[1], size, size, size)
    idx = coords[:, 1:] - low
    grid[0, :, idx[:, 0], idx[:, 1], idx[:, 2]] = feats.T
    return grid


def read_grid(grid, coords, low):
    idx = coords[:, 1:] - low
    return grid[0][:, idx[:, 0], idx[:, 1], idx[:, 2]].T


def conv3d_weight(weight, kernel_size):
    """Our ``(K, Cin, Cout)`` weight as ``conv3d``'s ``(Cout, Cin, k, k, k)``."""
    k = kernel_size
    return weight.permute(2, 1, 0).reshape(weight.shape[2], weight.shape[1], k, k, k)


def reference_submanifold(coords, feats, weight, kernel_size):
    """Dense ``conv3d`` on a grid, read at the active sites (inactive sites hold zeros)."""
    low = int(coords[:, 1:].min()) - kernel_size
    size = int(coords[:, 1:].max()) - low + kernel_size + 1
    grid = dense_grid(coords, feats, low, size)
    out = F.conv3d(grid, conv3d_weight(weight, kernel_size), padding=kernel_size // 2)
    return read_grid(out, coords, low)


def reference_strided(coords, feats, weight):
    """Loop: each fine site adds ``feats @ weight[octant]`` to its parent ``floor(site / 2)``."""
    out = {}
    for c, f in zip(coords.tolist(), feats, strict=True):
        parent = (c[0], *(v // 2 for v in c[1:]))
        octant = (c[1] % 2) * 4 + (c[2] % 2) * 2 + (c[3] % 2)
        out[parent] = out.get(parent, 0) + f @ weight[octant]
    return out


def reference_transposed(fine_coords, coarse_coords, coarse_feats, weight):
    """Loop: each fine site reads ``coarse_feats[parent] @ weight[octant]``."""
    row_of = {tuple(c): i for i, c in enumerate(coarse_coords.tolist())}
    rows = []
    for c in fine_coords.tolist():
        parent = (c[0], *(v // 2 for v in c[1:]))
        octant = (c[1] % 2) * 4 + (c[2] % 2) * 2 + (c[3] % 2)
        rows.append(coarse_feats[row_of[parent]] @ weight[octant])
    return torch.stack(rows)


@pytest.mark.parametrize("kernel_size", [1, 3, 5])
def test_submanifold_matches_dense_conv3d(generator, kernel_size):
    coords = random_sites(generator)
    feats = torch.randn(coords.shape[0], 3, generator=generator, dtype=F64)
    weight = torch.randn(kernel_size**3, 3, 5, generator=generator, dtype=F64)
    manager = CoordinateManager(coords)
    out = sparse_conv(feats, weight, manager.submanifold_map(1, kernel_size))
    ref = reference_submanifold(coords, feats, weight, kernel_size)
    torch.testing.assert_close(out, ref)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    density=st.floats(0.05, 0.9),
    low=st.integers(-7, 7),
    kernel_size=st.sampled_from([3, 5]),
)
def test_submanifold_property(seed, density, low, kernel_size):
    g = torch.Generator().manual_seed(seed)
    coords = random_sites(g, size=5, density=density, low=low)
    if coords.shape[0] == 0:
        return
    feats = torch.randn(coords.shape[0], 2, generator=g, dtype=F64)
    weight = torch.randn(kernel_size**3, 2, 3, generator=g, dtype=F64)
    out = sparse_conv(feats, weight, CoordinateManager(coords).submanifold_map(1, kernel_size))
    torch.testing.assert_close(out, reference_submanifold(coords, feats, weight, kernel_size))


def test_submanifold_at_coarser_stride_uses_coarse_neighbours(generator):
    coords = random_sites(generator, size=8, density=0.5)
    manager = CoordinateManager(coords)
    coarse = manager.coords(2)
    feats = torch.randn(coarse.shape[0], 2, generator=generator, dtype=F64)
    weight = torch.randn(27, 2, 3, generator=generator, dtype=F64)
    out = sparse_conv(feats, weight, manager.submanifold_map(2, 3))
    torch.testing.assert_close(out, reference_submanifold(coarse, feats, weight, 3))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), low=st.integers(-9, 9), batches=st.integers(1, 2))
def test_strided_matches_loop_reference(seed, low, batches):
    g = torch.Generator().manual_seed(seed)
    coords = random_sites(g, size=5, density=0.3, low=low, batches=batches)
    feats = torch.randn(coords.shape[0], 3, generator=g, dtype=F64)
    weight = torch.randn(8, 3, 4, generator=g, dtype=F64)
    manager = CoordinateManager(coords)
    out = sparse_conv(feats, weight, manager.downsample_map(1))
    coarse = manager.coords(2)
    ref = reference_strided(coords, feats, weight)
    assert sorted(map(tuple, coarse.tolist())) == sorted(ref)  # sites = unique(floor(site / 2))
    for row, site in zip(out, coarse.tolist(), strict=True):
        torch.testing.assert_close(row, ref[tuple(site)])


def test_strided_matches_dense_conv3d(generator):
    coords = random_sites(generator, size=8, density=0.3, low=-4)
    feats = torch.randn(coords.shape[0], 3, generator=generator, dtype=F64)
    weight = torch.randn(8, 3, 4, generator=generator, dtype=F64)
    manager = CoordinateManager(coords)
    out = sparse_conv(feats, weight, manager.downsample_map(1))
    low = -4  # even, so the dense stride-2 windows are the coarse cells
    dense = F.conv3d(dense_grid(coords, feats, low, 8), conv3d_weight(weight, 2), stride=2)
    torch.testing.assert_close(out, read_grid(dense, manager.coords(2), low // 2))


def test_transposed_matches_references(generator):
    coords = random_sites(generator, size=8, density=0.3, low=-4)
    manager = CoordinateManager(coords)
    coarse = manager.coords(2)
    feats = torch.randn(coarse.shape[0], 3, generator=generator, dtype=F64)
    weight = torch.randn(8, 3, 4, generator=generator, dtype=F64)
    out = sparse_conv(feats, weight, manager.upsample_map(2))
    assert out.shape == (coords.shape[0], 4)  # back onto the cached fine sites, in their order
    torch.testing.assert_close(out, reference_transposed(coords, coarse, feats, weight))
    grid = dense_grid(coarse, feats, -2, 4)
    dense_weight = weight.permute(1, 2, 0).reshape(3, 4, 2, 2, 2)
    dense = F.conv_transpose3d(grid, dense_weight, stride=2)
    torch.testing.assert_close(out, read_grid(dense, coords, -4))


def _gradcheck(feats, weight, kmap, bias):
    def fn(f, w, b):
        return sparse_conv(f, w, kmap, b)

    assert torch.autograd.gradcheck(fn, (feats, weight, bias))


@pytest.mark.parametrize("kind", ["submanifold3", "submanifold1", "strided", "transposed"])
def test_gradcheck(generator, kind):
    coords = random_sites(generator, size=3, density=0.5, low=-1, batches=2)
    manager = CoordinateManager(coords)
    if kind == "submanifold3":
        kmap = manager.submanifold_map(1, 3)
    elif kind == "submanifold1":
        kmap = manager.submanifold_map(1, 1)
    elif kind == "strided":
        kmap = manager.downsample_map(1)
    else:
        kmap = manager.upsample_map(2)
    feats = torch.randn(kmap.num_in, 2, generator=generator, dtype=F64, requires_grad=True)
    weight = torch.randn(kmap.num_offsets, 2, 3, generator=generator, dtype=F64, requires_grad=True)
    bias = torch.randn(3, generator=generator, dtype=F64, requires_grad=True)
    _gradcheck(feats, weight, kmap, bias)


def test_gradcheck_modules_and_batchnorm(generator):
    coords = random_sites(generator, size=3, density=0.6, low=0)
    x = SparseTensor.from_coords(
        coords, torch.randn(coords.shape[0], 2, generator=generator, dtype=F64)
    )
    layers = [
        SubmanifoldConv(2, 3, 3, bias=True),
        SparseBatchNorm(3),
        SparseReLU(),
        StridedConv(3, 2),
        TransposedConv(2, 2),
    ]
    for layer in layers:
        layer.to(F64)

    def fn(feats, *params):
        y = x.with_feats(feats)
        for layer in layers:
            y = layer(y)
        return y.feats

    feats = x.feats.clone().requires_grad_(True)
    params = [p for layer in layers for p in layer.parameters()]
    assert torch.autograd.gradcheck(fn, (feats, *params), fast_mode=True)


def test_kernel_maps_are_built_once_and_shared(generator):
    coords = random_sites(generator, size=6, density=0.4)
    x = SparseTensor.from_coords(coords, torch.randn(coords.shape[0], 4, generator=generator))
    conv_a, conv_b = SubmanifoldConv(4, 4), SubmanifoldConv(4, 4)
    down, up = StridedConv(4, 4), TransposedConv(4, 4)
    manager = x.manager
    y = conv_a(x)
    kmap = manager.submanifold_map(1, 3)
    conv_b(y)
    assert manager.submanifold_map(1, 3) is kmap
    z = down(y)
    assert z.stride == 2 and z.manager is manager
    assert manager.downsample_map(1) is manager.downsample_map(1)
    back = up(z)
    assert back.stride == 1 and torch.equal(back.coords, x.coords)
    assert manager.upsample_map(2) is manager.upsample_map(2)
    assert len(manager._maps) == 3


def test_batch_independence(generator):
    """Two clouds in one batch (overlapping xyz) give what each gives alone."""
    a = random_sites(generator, size=6, density=0.4)
    b = random_sites(generator, size=6, density=0.4)
    b[:, 0] = 1
    fa = torch.randn(a.shape[0], 3, generator=generator, dtype=F64)
    fb = torch.randn(b.shape[0], 3, generator=generator, dtype=F64)
    torch.manual_seed(0)
    conv, down, up = SubmanifoldConv(3, 4), StridedConv(4, 4), TransposedConv(4, 2)
    for layer in (conv, down, up):
        layer.to(F64)

    def run(coords, feats):
        x = SparseTensor.from_coords(coords, feats)
        mid = down(conv(x))
        return mid, up(mid).feats

    mid_ab, out_ab = run(torch.cat([a, b]), torch.cat([fa, fb]))
    mid_a, out_a = run(a, fa)
    b0 = b.clone()
    b0[:, 0] = 0
    mid_b, out_b = run(b0, fb)
    torch.testing.assert_close(out_ab, torch.cat([out_a, out_b]))
    assert mid_ab.feats.shape[0] == mid_a.feats.shape[0] + mid_b.feats.shape[0]


def test_row_order_equivariance(generator):
    coords = random_sites(generator, size=7, density=0.4, batches=2)
    feats = torch.randn(coords.shape[0], 3, generator=generator, dtype=F64)
    perm = torch.randperm(coords.shape[0], generator=generator)
    torch.manual_seed(0)
    conv, down, up = SubmanifoldConv(3, 4), StridedConv(4, 4), TransposedConv(4, 2)
    for layer in (conv, down, up):
        layer.to(F64)

    def run(c, f):
        return up(down(conv(SparseTensor.from_coords(c, f)))).feats

    torch.testing.assert_close(run(coords[perm], feats[perm]), run(coords, feats)[perm])


def test_deterministic_forward_and_backward(generator):
    coords = random_sites(generator, size=10, density=0.4, batches=2)
    feats = torch.randn(coords.shape[0], 16, generator=generator)
    torch.manual_seed(0)
    conv, down, up = SubmanifoldConv(16, 16), StridedConv(16, 16), TransposedConv(16, 16)

    def run():
        f = feats.clone().requires_grad_(True)
        out = up(down(conv(SparseTensor.from_coords(coords, f)))).feats
        out.square().sum().backward()
        grads = [f.grad] + [p.grad.clone() for m in (conv, down, up) for p in m.parameters()]
        for m in (conv, down, up):
            m.zero_grad()
        return out.detach(), grads

    out_1, grads_1 = run()
    out_2, grads_2 = run()
    assert torch.equal(out_1, out_2)
    assert all(torch.equal(g1, g2) for g1, g2 in zip(grads_1, grads_2, strict=True))


def test_batchnorm_uses_active_sites_only(generator):
    coords = random_sites(generator, size=6, density=0.2)
    feats = torch.randn(coords.shape[0], 3, generator=generator) * 2 + 1
    bn = SparseBatchNorm(3, momentum=1.0)
    out = bn(SparseTensor.from_coords(coords, feats)).feats
    mean = feats.mean(0)
    var = feats.var(0, unbiased=False)
    torch.testing.assert_close(out, (feats - mean) / torch.sqrt(var + bn.eps))
    torch.testing.assert_close(bn.running_mean, mean)
    torch.testing.assert_close(bn.running_var, feats.var(0, unbiased=True))


def test_empty_and_single_site():
    empty = torch.zeros(0, 4, dtype=torch.int64)
    x = SparseTensor.from_coords(empty, torch.zeros(0, 3))
    conv, down = SubmanifoldConv(3, 5, bias=True), StridedConv(3, 5)
    assert conv(x).feats.shape == (0, 5)
    assert down(x).feats.shape == (0, 5)
    assert TransposedConv(5, 2)(down(x)).feats.shape == (0, 2)

    one = torch.tensor([[0, -3, 5, 1]])
    feats = torch.randn(1, 3)
    x = SparseTensor.from_coords(one, feats)
    torch.testing.assert_close(conv(x).feats, feats @ conv.weight[13] + conv.bias)
    coarse = down(x)
    assert coarse.coords.tolist() == [[0, -2, 2, 0]]
    torch.testing.assert_close(coarse.feats, feats @ down.weight[4 + 2 + 1])  # odd x, y, z
    bn = SparseBatchNorm(3)
    with pytest.warns(RuntimeWarning, match="1 site"):
        out = bn(x).feats
    assert torch.isfinite(out).all()


def test_invalid_inputs():
    with pytest.raises(ShapeError, match="duplicate"):
        CoordinateManager(torch.tensor([[0, 1, 2, 3], [0, 1, 2, 3]]))
    with pytest.raises(ShapeError, match=r"\(N, 4\)"):
        CoordinateManager(torch.zeros(3, 3, dtype=torch.int64))
    with pytest.raises(ShapeError, match="int64"):
        CoordinateManager(torch.zeros(3, 4, dtype=torch.int32))
    with pytest.raises(ShapeError, match="odd"):
        kernel_offsets(2)
    manager = CoordinateManager(torch.tensor([[0, 0, 0, 0], [0, 0, 0, 1]]))
    kmap = manager.submanifold_map(1, 3)
    with pytest.raises(ShapeError, match="weight"):
        sparse_conv(torch.zeros(2, 3), torch.zeros(8, 3, 4), kmap)
    with pytest.raises(ShapeError, match="feats"):
        sparse_conv(torch.zeros(3, 3), torch.zeros(27, 3, 4), kmap)
    x = SparseTensor.from_coords(torch.tensor([[0, 0, 0, 0]]), torch.zeros(1, 2))
    with pytest.raises(ShapeError):
        sparse_cat(x, StridedConv(2, 2)(x))
    with pytest.raises(ShapeError, match="stride"):
        TransposedConv(2, 2)(x)


def test_far_coordinates_and_negative_batches_do_not_alias():
    coords = torch.tensor([[0, -(2**20), 0, 0], [0, 2**20, 0, 0], [3, 0, 0, 1], [3, 0, 0, 0]])
    feats = torch.eye(4, dtype=F64)
    weight = torch.randn(27, 4, 1, dtype=F64)
    out = sparse_conv(feats, weight, CoordinateManager(coords).submanifold_map(1, 3))
    torch.testing.assert_close(out, reference_submanifold_by_loop(coords, feats, weight))


def reference_submanifold_by_loop(coords, feats, weight):
    row_of = {tuple(c): i for i, c in enumerate(coords.tolist())}
    offsets = kernel_offsets(3).tolist()
    rows = []
    for c in coords.tolist():
        acc = feats.new_zeros(weight.shape[2])
        for k, d in enumerate(offsets):
            j = row_of.get((c[0], c[1] + d[0], c[2] + d[1], c[3] + d[2]))
            if j is not None:
                acc = acc + feats[j] @ weight[k]
        rows.append(acc)
    return torch.stack(rows)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(generator):
    coords = random_sites(generator, size=8, density=0.4, batches=2)
    feats = torch.randn(coords.shape[0], 8, generator=generator)
    torch.manual_seed(0)
    layers = [SubmanifoldConv(8, 8), StridedConv(8, 8), TransposedConv(8, 4, bias=True)]

    def run(device):
        x = SparseTensor.from_coords(coords.to(device), feats.to(device))
        for layer in layers:
            x = layer.to(device)(x)
        return x.feats.cpu()

    torch.testing.assert_close(run("cuda"), run("cpu"), rtol=1e-4, atol=1e-4)


def test_autocast_runs_in_the_autocast_dtype(generator):
    coords = random_sites(generator, size=6, density=0.4)
    feats = torch.randn(coords.shape[0], 4, generator=generator)
    conv = SubmanifoldConv(4, 3, bias=True)
    x = SparseTensor.from_coords(coords, feats.requires_grad_(True))
    reference = conv(x).feats
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = conv(x).feats
    assert out.dtype == torch.bfloat16
    torch.testing.assert_close(out.float(), reference, rtol=0.05, atol=0.05)
    out.float().sum().backward()
    assert feats.grad.dtype == torch.float32 and torch.isfinite(conv.weight.grad).all()


def test_table_and_binary_search_lookups_agree(generator, monkeypatch):
    coords = random_sites(generator, size=7, density=0.4, low=-5, batches=2)
    feats = torch.randn(coords.shape[0], 3, generator=generator, dtype=F64)
    weight = torch.randn(27, 3, 2, generator=generator, dtype=F64)
    with_table = sparse_conv(feats, weight, CoordinateManager(coords).submanifold_map(1, 3))
    monkeypatch.setattr(sparse_module, "TABLE_MAX_CELLS", 0)
    manager = CoordinateManager(coords)
    assert manager._site_set(1).table is None
    torch.testing.assert_close(
        sparse_conv(feats, weight, manager.submanifold_map(1, 3)), with_table
    )
    with pytest.raises(ShapeError, match="duplicate"):
        CoordinateManager(torch.cat([coords, coords[:1]]))
