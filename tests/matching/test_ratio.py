import warnings

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import byoc_cli.matching.ratio as ratio_mod
from byoc_cli.errors import ShapeError
from byoc_cli.matching import (
    KNN,
    Correspondences,
    feature_knn,
    mutual_filter,
    ratio_test_correspondences,
)

F64 = torch.float64


def unit(n, c, generator, dtype=torch.float32):
    return torch.nn.functional.normalize(torch.randn(n, c, generator=generator, dtype=dtype), dim=1)


# --- naive references -------------------------------------------------------------------


def naive_dist(a, b):
    """Full (N, M) matrix of |a - b|^2 / 2, one pair at a time in float64."""
    a, b = a.double(), b.double()
    return ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1) / 2


def naive_knn(a, b, k):
    d = naive_dist(a, b)
    order = torch.argsort(d, dim=1, stable=True)[:, :k]
    return d.gather(1, order), order


def naive_ratio(a, b, k):
    """Reference ratio test with Python loops: list of (src, tgt, weight) rows."""
    rows = []
    for d, forward in ((naive_dist(a, b), True), (naive_dist(b, a), False)):
        direction = []
        for i in range(d.shape[0]):
            order = sorted(range(d.shape[1]), key=lambda j, i=i: float(d[i, j]))
            d1 = max(float(d[i, order[0]]), 1e-9)
            d2 = max(float(d[i, order[1]]), 1e-9)
            w = 1.0 - d1 / d2
            direction.append((i, order[0], w) if forward else (order[0], i, w))
        direction.sort(key=lambda row: -row[2])
        rows += direction[:k]
    return rows


# --- hand-worked example -----------------------------------------------------------------

# tgt on the unit circle: t0 = (1, 0), t1 = (0, 1), t2 = (-1, 0); src: s0 = (1, 0), s1 = (.6, .8).
# D = 1 - cos:  s0 -> (t0, t1, t2) = (0, 1, 2);  s1 -> (0.4, 0.2, 1.6).
# src -> tgt: s0: nn1 t0 (D 0 -> 1e-9), nn2 t1 (1)  -> w = 1 - 1e-9
#             s1: nn1 t1 (0.2), nn2 t0 (0.4)        -> w = 0.5
# tgt -> src: t0: nn1 s0 (1e-9), nn2 s1 (0.4)       -> w = 1 - 2.5e-9
#             t1: nn1 s1 (0.2), nn2 s0 (1)          -> w = 0.8
#             t2: nn1 s1 (1.6), nn2 s0 (2)          -> w = 0.2
HAND_SRC = torch.tensor([[1.0, 0.0], [0.6, 0.8]], dtype=F64)
HAND_TGT = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]], dtype=F64)


def test_hand_worked_ratio_test():
    corr = ratio_test_correspondences(HAND_SRC, HAND_TGT, k=200)
    assert corr.src_idx.tolist() == [0, 1, 0, 1, 1]
    assert corr.tgt_idx.tolist() == [0, 1, 0, 1, 2]
    expected = torch.tensor([1 - 1e-9, 0.5, 1 - 2.5e-9, 0.8, 0.2], dtype=F64)
    torch.testing.assert_close(corr.weight, expected, rtol=0, atol=1e-12)


def test_hand_worked_top_k_and_mutual():
    corr = ratio_test_correspondences(HAND_SRC, HAND_TGT, k=1)
    assert corr.src_idx.tolist() == [0, 0]
    assert corr.tgt_idx.tolist() == [0, 0]
    mutual = ratio_test_correspondences(HAND_SRC, HAND_TGT, k=200, mutual=True)
    # t2's nearest source point is s1, but s1's nearest target point is t1
    assert mutual.src_idx.tolist() == [0, 1, 0, 1]
    assert mutual.tgt_idx.tolist() == [0, 1, 0, 1]


def test_hand_worked_knn():
    knn = feature_knn(HAND_SRC, HAND_TGT, k=3)
    assert isinstance(knn, KNN)
    assert knn.idx.tolist() == [[0, 1, 2], [1, 0, 2]]
    expected = torch.tensor([[0.0, 1.0, 2.0], [0.2, 0.4, 1.6]], dtype=F64)
    torch.testing.assert_close(knn.dist, expected)


def test_mutual_filter_function():
    corr = ratio_test_correspondences(HAND_SRC, HAND_TGT, k=200)
    nn_st = feature_knn(HAND_SRC, HAND_TGT, k=1).idx[:, 0]
    nn_ts = feature_knn(HAND_TGT, HAND_SRC, k=1).idx[:, 0]
    kept = mutual_filter(corr, nn_st, nn_ts)
    assert kept.src_idx.tolist() == [0, 1, 0, 1]
    assert kept.tgt_idx.tolist() == [0, 1, 0, 1]
    torch.testing.assert_close(kept.weight, corr.weight[:4])


# --- agreement with the references ---------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(0, 40),
    m=st.integers(0, 40),
    k=st.integers(0, 5),
    c=st.integers(3, 16),  # 1-D unit features are +-1: ties
    seed=st.integers(0, 2**31 - 1),
)
def test_knn_matches_naive_reference(n, m, k, c, seed):
    g = torch.Generator().manual_seed(seed)
    a, b = unit(n, c, g, F64), unit(m, c, g, F64)
    knn = feature_knn(a, b, k=k)
    ref_d, ref_i = naive_knn(a, b, k)
    assert knn.idx.dtype == torch.int64
    assert knn.idx.shape == knn.dist.shape == (n, min(k, m))
    torch.testing.assert_close(knn.dist, ref_d)
    assert torch.equal(knn.idx, ref_i)


@settings(max_examples=20, deadline=None)
@given(
    n=st.integers(2, 30), m=st.integers(2, 30), k=st.integers(1, 40), seed=st.integers(0, 2**31 - 1)
)
def test_ratio_matches_naive_reference(n, m, k, seed):
    g = torch.Generator().manual_seed(seed)
    a, b = unit(n, 8, g, F64), unit(m, 8, g, F64)
    corr = ratio_test_correspondences(a, b, k=k)
    rows = naive_ratio(a, b, k)
    assert len(rows) == min(k, n) + min(k, m)
    assert corr.src_idx.tolist() == [r[0] for r in rows]
    assert corr.tgt_idx.tolist() == [r[1] for r in rows]
    torch.testing.assert_close(corr.weight, torch.tensor([r[2] for r in rows], dtype=F64))


@settings(max_examples=20, deadline=None)
@given(
    n=st.integers(1, 60),
    m=st.integers(2, 60),
    chunk=st.integers(1, 70),
    seed=st.integers(0, 2**31 - 1),
)
def test_chunked_knn_equals_unchunked(n, m, chunk, seed):
    g = torch.Generator().manual_seed(seed)
    a, b = unit(n, 32, g), unit(m, 32, g)
    full = feature_knn(a, b, k=2, chunk_size=10**6)
    part = feature_knn(a, b, k=2, chunk_size=chunk)
    assert torch.equal(full.idx, part.idx)
    assert torch.equal(full.dist, part.dist)
    with warnings.catch_warnings():
        # n == 1: the ratio test warns that it has no second neighbour (tested elsewhere)
        warnings.simplefilter("ignore", UserWarning)
        c_full = ratio_test_correspondences(a, b, k=5, chunk_size=10**6)
        c_part = ratio_test_correspondences(a, b, k=5, chunk_size=chunk)
    for x, y in zip(c_full, c_part, strict=True):
        assert torch.equal(x, y)


def test_automatic_chunking_follows_the_byte_budget(monkeypatch):
    g = torch.Generator().manual_seed(3)
    a, b = unit(300, 32, g), unit(200, 32, g)
    full = feature_knn(a, b, k=4)
    calls = []
    real_topk = torch.topk

    def counting_topk(*args, **kwargs):
        calls.append(args[0].shape)
        return real_topk(*args, **kwargs)

    # 200 reference rows * 4 bytes * 7 rows per chunk
    monkeypatch.setattr(ratio_mod, "CHUNK_BYTES", 200 * 4 * 7)
    monkeypatch.setattr(torch, "topk", counting_topk)
    small = feature_knn(a, b, k=4)
    monkeypatch.undo()
    assert max(shape[0] for shape in calls) == 7
    assert len(calls) == -(-300 // 7)
    assert torch.equal(full.idx, small.idx)


def test_permuting_target_permutes_indices(generator):
    a, b = unit(30, 16, generator), unit(25, 16, generator)
    perm = torch.randperm(25, generator=generator)
    knn = feature_knn(a, b, k=3)
    knn_p = feature_knn(a, b[perm], k=3)
    assert torch.equal(perm[knn_p.idx], knn.idx)
    torch.testing.assert_close(knn_p.dist, knn.dist)


# --- properties of the weights -----------------------------------------------------------


@settings(max_examples=20, deadline=None)
@given(n=st.integers(2, 80), m=st.integers(2, 80), seed=st.integers(0, 2**31 - 1))
def test_weights_in_unit_interval_and_rows_typed(n, m, seed):
    g = torch.Generator().manual_seed(seed)
    a, b = unit(n, 32, g), unit(m, 32, g)
    corr = ratio_test_correspondences(a, b, k=10)
    assert isinstance(corr, Correspondences)
    assert corr.src_idx.dtype == corr.tgt_idx.dtype == torch.int64
    assert corr.weight.dtype == torch.float32
    assert (
        corr.src_idx.shape == corr.tgt_idx.shape == corr.weight.shape == (min(10, n) + min(10, m),)
    )
    assert bool((corr.weight >= 0).all() & (corr.weight <= 1).all())
    assert bool((corr.src_idx < n).all() & (corr.tgt_idx < m).all())
    first = min(10, n)
    # each direction sorted by decreasing weight; the src -> tgt rows cover distinct sources
    assert bool((corr.weight[:first].diff() <= 0).all() & (corr.weight[first:].diff() <= 0).all())
    assert corr.src_idx[:first].unique().numel() == first
    assert corr.tgt_idx[first:].unique().numel() == min(10, m)


def test_duplicate_features_get_zero_weight():
    a = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    b = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # t0 == t1: nn1 and nn2 tie at 0
    corr = ratio_test_correspondences(a, b, k=2)
    # src -> tgt: s1 -> t2 (D 0 vs 1: w = 1 - 1e-9), then s0 (D 0 vs 0: w = 0)
    assert corr.src_idx[:2].tolist() == [1, 0]
    assert corr.weight[0].item() == pytest.approx(1 - 1e-9)
    assert corr.weight[1].item() == 0.0


def test_gradcheck_ratio_weights():
    g = torch.Generator().manual_seed(5)
    a = unit(7, 4, g, F64).requires_grad_()
    b = unit(6, 4, g, F64).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda x, y: ratio_test_correspondences(x, y, k=4).weight, (a, b), eps=1e-6, atol=1e-6
    )


def test_gradcheck_knn_distances():
    g = torch.Generator().manual_seed(6)
    a = torch.randn(5, 3, generator=g, dtype=F64, requires_grad=True)
    b = torch.randn(8, 3, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, y: feature_knn(x, y, k=3).dist, (a, b))


def test_weights_backpropagate_to_both_feature_sets(generator):
    a = unit(50, 32, generator).requires_grad_()
    b = unit(40, 32, generator).requires_grad_()
    ratio_test_correspondences(a, b, k=10).weight.sum().backward()
    assert a.grad is not None and a.grad.abs().sum() > 0
    assert b.grad is not None and b.grad.abs().sum() > 0


# --- degenerate sizes, errors, determinism -----------------------------------------------


@pytest.mark.parametrize(("n", "m"), [(0, 0), (0, 5), (5, 0), (1, 5), (5, 1), (1, 1)])
def test_fewer_than_two_points_gives_typed_empty_result(n, m, generator):
    a, b = unit(n, 8, generator, F64), unit(m, 8, generator, F64)
    with pytest.warns(UserWarning, match="at least 2 points"):
        corr = ratio_test_correspondences(a, b)
    assert corr.src_idx.shape == corr.tgt_idx.shape == corr.weight.shape == (0,)
    assert corr.src_idx.dtype == corr.tgt_idx.dtype == torch.int64
    assert corr.weight.dtype == F64


def test_k_zero_is_empty_without_warning(generator):
    a, b = unit(5, 8, generator), unit(6, 8, generator)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        corr = ratio_test_correspondences(a, b, k=0)
    assert corr.weight.shape == (0,) and corr.weight.dtype == torch.float32


def test_empty_result_keeps_the_graph(generator):
    a = unit(1, 8, generator).requires_grad_()
    b = unit(5, 8, generator).requires_grad_()
    with pytest.warns(UserWarning):
        corr = ratio_test_correspondences(a, b)
    corr.weight.sum().backward()  # no "does not require grad" error
    assert a.grad is not None


def test_k_larger_than_clouds(generator):
    a, b = unit(3, 8, generator), unit(4, 8, generator)
    corr = ratio_test_correspondences(a, b, k=200)
    assert corr.weight.shape == (7,)
    assert feature_knn(a, b, k=10).idx.shape == (3, 4)


def test_shape_errors(generator):
    a = unit(5, 8, generator)
    with pytest.raises(ShapeError):
        feature_knn(a, unit(5, 7, generator))
    with pytest.raises(ShapeError):
        feature_knn(a[0], a)
    with pytest.raises(ShapeError):
        ratio_test_correspondences(a.long(), a.long())
    with pytest.raises(ValueError, match="k must be"):
        ratio_test_correspondences(a, a, k=-1)
    with pytest.raises(ValueError, match="chunk_size"):
        feature_knn(a, a, chunk_size=0)


def test_deterministic(generator):
    a, b = unit(500, 32, generator), unit(400, 32, generator)
    first = ratio_test_correspondences(a, b, k=50)
    second = ratio_test_correspondences(a.clone(), b.clone(), k=50)
    for x, y in zip(first, second, strict=True):
        assert torch.equal(x, y)


def test_the_two_directions_side_by_side_give_the_same_correspondences():
    from byoc_cli.threads import side_by_side, worker_pool

    g = torch.Generator().manual_seed(3)
    a = torch.nn.functional.normalize(torch.randn(700, 16, generator=g), dim=1)
    b = torch.nn.functional.normalize(torch.randn(500, 16, generator=g), dim=1)
    alone = ratio_test_correspondences(a, b, k=50)
    pool = worker_pool(2)
    try:
        split = ratio_test_correspondences(a, b, k=50, parallel=side_by_side(pool))
    finally:
        pool.shutdown()
    for x, y in zip(alone, split, strict=True):
        assert torch.equal(x, y)


@settings(max_examples=40, deadline=None)
@given(
    rows=st.integers(1, 20),
    cols=st.integers(2, 30),
    k=st.integers(1, 3),
    levels=st.integers(1, 6),  # few distinct values: ties
    nan_row=st.booleans(),
    mixed=st.booleans(),
    dtype=st.sampled_from([torch.float32, torch.float64]),
    seed=st.integers(0, 2**31 - 1),
)
def test_smallest_columns_give_topks_values(rows, cols, k, levels, nan_row, mixed, dtype, seed):
    g = torch.Generator().manual_seed(seed)
    score = torch.rand(rows, cols, generator=g, dtype=dtype)
    if levels < 6:  # few distinct values: ties, which go to topk (mixed: every other row)
        tied = torch.randint(0, levels, (rows, cols), generator=g).to(dtype)
        score[:: 2 if mixed else 1] = tied[:: 2 if mixed else 1]
    k = min(k, cols)  # feature_knn's clip
    if nan_row:
        score[0, cols // 2] = float("nan")
    expected = torch.topk(score, k, dim=1, largest=False, sorted=True).indices
    given = score.clone()
    columns = ratio_mod._smallest_columns(given, k)
    assert columns.dtype == torch.int64 and columns.shape == (rows, k)
    assert torch.equal(columns, expected)
    torch.testing.assert_close(given, score, rtol=0, atol=0, equal_nan=True)  # left as it came
