"""Surface normals from cell moments: against a brute-force reference, on planes and spheres,
and the closed-form smallest eigenvector against ``eigh``."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.geometry import neighbors
from byoc_cli.geometry.neighbors import _cells, grid_origin
from byoc_cli.geometry.normals import _cell_normals, smallest_eigenvector, surface_normals


def _reference(queries, size, points):
    """Normals and counts of the 27-cell boxes by brute force: every point's cell compared
    with every query's (the definition of :func:`_cell_normals`)."""
    origin = grid_origin(points, size)
    qc, pc = _cells(queries, size, origin), _cells(points, size, origin)
    inside = ((qc[:, None, :] - pc[None, :, :]).abs() <= 1).all(dim=2)  # (Q, N)
    normals, counts = [], []
    for row in inside:
        box = points[row]
        counts.append(len(box))
        if len(box) < 3:
            normals.append(None)
            continue
        cov = torch.cov(box.T, correction=0)
        normals.append(torch.linalg.eigh(cov).eigenvectors[:, 0])
    return normals, torch.tensor(counts, dtype=torch.float64)


def _clusters(seed: int, n: int = 400) -> torch.Tensor:
    """Patches of a few planes and stray points, dense and sparse (``(n, 3)``)."""
    g = torch.Generator().manual_seed(seed)
    centres = (torch.rand(6, 3, generator=g, dtype=torch.float64) - 0.5) * 2.0
    which = torch.randint(0, 6, (n,), generator=g)
    spread = torch.tensor([0.2, 0.2, 0.004], dtype=torch.float64)
    points = centres[which] + torch.randn(n, 3, generator=g, dtype=torch.float64) * spread
    return torch.cat([points, (torch.rand(12, 3, generator=g, dtype=torch.float64) - 0.5) * 3])


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), size=st.sampled_from([0.05, 0.1, 0.3]), part=st.floats(0, 1))
def test_cell_normals_match_the_brute_force_boxes(seed, size, part):
    points = _clusters(seed)
    g = torch.Generator().manual_seed(seed + 1)
    some = points[torch.rand(len(points), generator=g) < part]  # queries: a part of them
    for queries, of in ((points, None), (some, points)):
        normals, counts = _cell_normals(queries, size, of)
        ref, ref_counts = _reference(queries, size, points)
        assert torch.equal(counts, ref_counts)
        for normal, expected, count in zip(normals, ref, ref_counts, strict=True):
            if expected is not None and count >= 8:
                assert abs(float(normal @ expected)) == pytest.approx(1.0, abs=1e-6)


def test_a_part_of_the_points_gets_the_normals_of_the_whole(monkeypatch):
    """Queries among other points (the widened boxes) read the sums over all the points, to
    the bit, whether the boxes' positions come from a dense table or from binary searches."""
    points = _clusters(3, 3000)
    weak = points[::7]
    whole = _cell_normals(points, 0.1)
    part = _cell_normals(weak, 0.1, points, points.mean(dim=0))
    assert torch.equal(part[0], whole[0][::7]) and torch.equal(part[1], whole[1][::7])
    monkeypatch.setattr(neighbors.DenseCells, "build", staticmethod(lambda *a, **k: None))
    sparse = _cell_normals(points, 0.1)
    assert torch.equal(sparse[0], whole[0]) and torch.equal(sparse[1], whole[1])


def test_normals_of_no_points_and_of_one():
    empty = torch.zeros(0, 3, dtype=torch.float64)
    assert surface_normals(empty, 0.1).shape == (0, 3)
    one = surface_normals(torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64), 0.1)
    assert one.shape == (1, 3) and torch.isfinite(one).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_normals_of_a_noisy_plane_and_a_sphere(seed):
    g = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0)
    basis = torch.linalg.qr(
        torch.cat([normal[:, None], torch.randn(3, 2, dtype=torch.float64, generator=g)], 1)
    ).Q
    uv = (torch.rand(20_000, 2, generator=g, dtype=torch.float64) - 0.5) * 2.0
    plane = (
        uv @ basis[:, 1:].T
        + 0.002 * torch.randn(20_000, 1, generator=g, dtype=torch.float64) * normal
    )
    n = surface_normals(plane, 0.03)
    assert (n.norm(dim=1) - 1).abs().max() < 1e-9
    cos = (n @ normal).abs()
    assert float(cos.median()) > math.cos(math.radians(2))
    assert float(cos.quantile(0.01)) > math.cos(math.radians(10))  # thin cells at the rim
    sphere = torch.nn.functional.normalize(
        torch.randn(40_000, 3, generator=g, dtype=torch.float64), dim=1
    )
    n = surface_normals(sphere, 0.03)
    assert float((n * sphere).sum(1).abs().median()) > math.cos(math.radians(3))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), flat=st.sampled_from([1.0, 1e-3, 1e-6, 0.0]))
def test_smallest_eigenvector_matches_eigh(seed, flat):
    g = torch.Generator().manual_seed(seed)
    R = torch.linalg.qr(torch.randn(64, 3, 3, generator=g, dtype=torch.float64)).Q
    lam = torch.rand(64, 3, generator=g, dtype=torch.float64) + 0.1
    lam[:, 0] = lam[:, 0] * flat  # from isotropic-ish to exactly planar
    A = R @ torch.diag_embed(lam) @ R.transpose(1, 2)
    v = smallest_eigenvector(A)
    ref = torch.linalg.eigh(A).eigenvectors[:, :, 0]
    assert torch.allclose(v.norm(dim=1), torch.ones(64, dtype=torch.float64))
    # the residual of the eigen-equation is what matters where eigenvalues are close
    smallest = torch.linalg.eigvalsh(A)[:, 0]
    residual = (A @ v[:, :, None])[:, :, 0] - smallest[:, None] * v
    assert float(residual.norm(dim=1).max()) < 1e-8
    separated = (torch.linalg.eigvalsh(A)[:, 1] - smallest) > 1e-3
    assert torch.allclose(
        (v * ref).sum(1).abs()[separated],
        torch.ones(int(separated.sum()), dtype=torch.float64),
        atol=1e-8,
    )


def test_smallest_eigenvector_of_isotropic_and_double_roots():
    A = torch.stack(
        [torch.eye(3), torch.diag(torch.tensor([1.0, 1.0, 5.0])), torch.zeros(3, 3)]
    ).double()
    v = smallest_eigenvector(A)
    assert torch.allclose(v.norm(dim=1), torch.ones(3, dtype=torch.float64))
    assert abs(float(v[1, 2])) < 1e-9  # in the plane of the double root
