"""The degeneracy-aware point-to-plane step: recovery, held directions, degenerate input."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.fitting.point_to_plane import point_to_plane_step, point_to_plane_steps
from byoc_cli.geometry.transforms import apply_transform
from tests.fitting._surfaces import box_surface, motion


def _iterate(p, q, n, steps=10, degeneracy=0.05):
    T = torch.eye(4, dtype=torch.float64)
    for _ in range(steps):
        step = point_to_plane_step(apply_transform(T, p), q, n, degeneracy=degeneracy)
        T = step.T @ T
    return T, step


def test_recovers_a_known_motion_on_a_box(generator):
    q, n = box_surface(3000, generator)
    T_true = motion(4.0, [0.03, -0.02, 0.01])  # maps p onto q
    p = apply_transform(torch.linalg.inv(T_true), q)
    T, step = _iterate(p, q, n)
    assert torch.allclose(T, T_true, atol=1e-8)
    assert step.rank == 6


def test_a_plane_holds_the_sliding_directions_and_fixes_the_others(generator):
    # a floor: only z translation and the tilts about x and y are observable
    q = torch.rand(2000, 3, generator=generator, dtype=torch.float64) - 0.5
    q[:, 2] = 0.0
    n = torch.zeros_like(q)
    n[:, 2] = 1.0
    p = q + torch.tensor([0.05, 0.04, 0.02], dtype=torch.float64)  # slid 5 cm and 4 cm, 2 cm up
    T, step = _iterate(p, q, n, steps=3)
    assert step.rank == 3
    assert torch.allclose(T[:3, 3], torch.tensor([0.0, 0.0, -0.02], dtype=torch.float64))
    assert torch.allclose(T[:3, :3], torch.eye(3, dtype=torch.float64), atol=1e-12)


def test_a_weakly_constrained_direction_moves_without_the_hold_and_not_with_it(generator):
    # a floor with a low ridge: sliding across the ridge is constrained only by the ridge
    q, n = box_surface(4000, generator)
    q, n = q[n[:, 2] > 0.5], n[n[:, 2] > 0.5]  # the top face only
    ridge = torch.rand(10, 3, generator=generator, dtype=torch.float64) * 0.02
    ridge[:, 0] = 0.0
    q = torch.cat([q, ridge])
    n = torch.cat([n, torch.tensor([[1.0, 0.0, 0.0]]).double().expand(10, 3)])
    shift = torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64)
    plain = point_to_plane_step(q + shift, q, n, degeneracy=0.0, sliding=0.0)
    held = point_to_plane_step(q + shift, q, n, degeneracy=0.05, sliding=0.0)
    assert plain.rank > held.rank
    assert plain.T[0, 3] == pytest.approx(-0.01, abs=1e-9)
    assert abs(float(held.T[0, 3])) < 1e-3  # slides less than a tenth of the shift


def test_no_points_or_zero_weights_give_the_identity():
    empty = torch.zeros(0, 3, dtype=torch.float64)
    step = point_to_plane_step(empty, empty, empty)
    assert step.rank == 0 and torch.equal(step.T, torch.eye(4, dtype=torch.float64))
    p = torch.ones(5, 3, dtype=torch.float64)
    step = point_to_plane_step(p, p, p, weights=torch.zeros(5))
    assert step.rank == 0 and torch.equal(step.T, torch.eye(4, dtype=torch.float64))


def test_shapes_are_checked():
    with pytest.raises(ShapeError):
        point_to_plane_step(torch.zeros(4, 3), torch.zeros(5, 3), torch.zeros(4, 3))
    with pytest.raises(ShapeError):
        point_to_plane_step(torch.zeros(4, 2), torch.zeros(4, 2), torch.zeros(4, 2))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), degeneracy=st.sampled_from([0.0, 0.01, 0.05, 0.5]))
def test_every_step_is_a_proper_rigid_transform(seed, degeneracy):
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(30, 3, generator=g, dtype=torch.float64)
    q = torch.randn(30, 3, generator=g, dtype=torch.float64)
    n = torch.nn.functional.normalize(torch.randn(30, 3, generator=g, dtype=torch.float64), dim=1)
    step = point_to_plane_step(p, q, n, degeneracy=degeneracy)
    R = step.T[:3, :3]
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-9)
    assert float(torch.linalg.det(R)) == pytest.approx(1.0, abs=1e-9)
    assert torch.isfinite(step.T).all() and 0 <= step.rank <= 6


def test_sliding_holds_a_translation_that_few_surfaces_face(generator):
    # a floor and a strip of wall facing x: 1.5 % of the normals constrain x
    q = torch.rand(2000, 3, generator=generator, dtype=torch.float64) - 0.5
    q[:, 2] = 0.0
    wall = torch.rand(30, 3, generator=generator, dtype=torch.float64) * 0.1
    wall[:, 0] = 0.5
    n = torch.cat(
        [torch.tensor([[0.0, 0.0, 1.0]]).expand(2000, 3), torch.tensor([[1.0, 0, 0]]).expand(30, 3)]
    ).double()
    q = torch.cat([q, wall])
    shift = torch.tensor([0.03, 0.0, 0.01], dtype=torch.float64)
    free = point_to_plane_step(q + shift, q, n, sliding=0.0)
    held = point_to_plane_step(q + shift, q, n, sliding=0.025)
    centre = (q + shift).mean(0, keepdim=True)  # the step moves the centroid by its translation
    assert float((apply_transform(free.T, centre) - centre)[0, 0]) == pytest.approx(-0.03, abs=1e-6)
    moved = apply_transform(held.T, centre) - centre
    assert float(moved[0, 0]) == pytest.approx(0.0, abs=1e-12)
    assert float(moved[0, 2]) == pytest.approx(-0.01, abs=1e-6)  # the floor still lifts it back


@pytest.mark.parametrize("degeneracy", [0.0, 0.05])
def test_batched_steps_agree_with_one_step_each(generator, degeneracy):
    # a box, a plane (sliding held), a box seen in part (weights 0), and nothing at all
    p, n = box_surface(400, generator)
    plane_p = p.clone()
    plane_p[:, 2] = 0.0
    plane_n = torch.zeros_like(n)
    plane_n[:, 2] = 1.0
    P = torch.stack([p, plane_p, p, p])
    N = torch.stack([n, plane_n, n, n])
    Q = apply_transform(motion(3.0, [0.02, -0.01, 0.03]), P)
    W = torch.ones(4, 400, dtype=torch.float64)
    W[2, ::3] = 0.0
    W[3] = 0.0
    steps = point_to_plane_steps(P, Q, N, W, degeneracy=degeneracy)
    assert steps.shape == (4, 4, 4)
    for s in range(3):
        keep = W[s] > 0
        one = point_to_plane_step(P[s][keep], Q[s][keep], N[s][keep], degeneracy=degeneracy)
        assert torch.allclose(steps[s], one.T, atol=1e-12)
    assert torch.equal(steps[3], torch.eye(4, dtype=torch.float64))
    arrays = point_to_plane_steps(*(x.numpy() for x in (P, Q, N, W)), degeneracy=degeneracy)
    assert torch.equal(arrays, steps)  # arrays and tensors: the same steps


def test_batched_steps_check_their_shapes():
    p = torch.zeros(2, 5, 3, dtype=torch.float64)
    with pytest.raises(ShapeError):
        point_to_plane_steps(p, p, p, torch.ones(2, 4))
    with pytest.raises(ShapeError):
        point_to_plane_steps(p[0], p[0], p[0], torch.ones(5))


def test_arrays_give_the_step_tensors_give(generator):
    q, n = box_surface(200, generator)
    p = apply_transform(torch.linalg.inv(motion(3.0, [0.02, 0.01, -0.03])), q)
    w = torch.rand(200, generator=generator, dtype=torch.float64)
    for weights in (None, w):
        tensors = point_to_plane_step(p, q, n, weights, degeneracy=0.05)
        arrays = point_to_plane_step(
            p.numpy(), q.numpy(), n.numpy(), None if weights is None else weights.numpy(), 0.05
        )
        assert torch.equal(arrays.T, tensors.T) and arrays.rank == tensors.rank
        assert torch.equal(arrays.eigenvalues, tensors.eigenvalues)
