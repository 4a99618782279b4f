"""Coarse-to-fine point-to-plane refinement: recovery, the held direction of a corridor."""

from __future__ import annotations

import math

import pytest
import torch

from byoc_cli.geometry.transforms import (
    apply_transform,
    axis_angle_to_matrix,
    invert_transform,
    make_transform,
)
from byoc_cli.pipeline import refine as refine_module
from byoc_cli.pipeline import refine_pairs
from byoc_cli.pipeline import restarts as restarts_module
from byoc_cli.pipeline.refine import RefineCloud, measure_fit, refine_multiscale
from byoc_cli.pipeline.restarts import (
    Restarts,
    refine_starts,
    restart_refinement,
    restart_starts,
)
from byoc_cli.threads import side_by_side, worker_pool


def _boxes(n: int, boxes, generator: torch.Generator) -> torch.Tensor:
    """``(n, 3)`` points spread over the faces of axis-aligned ``boxes`` ((lo, hi) pairs)."""
    out = []
    for lo, hi in boxes:
        lo, hi = torch.tensor(lo).double(), torch.tensor(hi).double()
        m = n // len(boxes)
        p = lo + torch.rand(m, 3, generator=generator, dtype=torch.float64) * (hi - lo)
        face = torch.randint(0, 6, (m,), generator=generator)
        axis = face // 2
        p[torch.arange(m), axis] = torch.where(face % 2 == 0, lo[axis], hi[axis])
        out.append(p)
    return torch.cat(out)


def _pose_error(T, T_ref):
    delta = invert_transform(T_ref) @ T
    cos = (torch.trace(delta[:3, :3]) - 1) / 2
    return math.degrees(math.acos(float(cos.clamp(-1, 1)))), float(delta[:3, 3].norm())


ROOM = [([-1.5, -1.2, 0.0], [1.5, 1.2, 2.0]), ([-0.4, -0.3, 0.0], [0.3, 0.2, 0.7])]


def _motion(rotvec, t) -> torch.Tensor:
    return make_transform(
        axis_angle_to_matrix(torch.tensor(rotvec, dtype=torch.float64)),
        torch.tensor(t, dtype=torch.float64),
    )


def _room_pair(n: int, T_true: torch.Tensor, generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``(src, tgt)``: two samplings of ROOM, the source moved by ``T_true``'s inverse."""
    tgt = _boxes(n, ROOM, generator)
    return apply_transform(invert_transform(T_true), _boxes(n, ROOM, generator)), tgt


def test_recovers_a_known_motion_from_a_rough_start(generator):
    T_true = _motion([0.1, 0.3, -0.2], [0.2, -0.1, 0.05])
    src, tgt = _room_pair(60_000, T_true, generator)
    nudge = _motion([0.0, 0.0, math.radians(3.0)], [0.04, -0.03, 0.0])
    out = refine_multiscale(src, tgt, nudge @ T_true, voxel_size=0.025)
    rot, trans = _pose_error(out.T_tgt_src, T_true)
    assert _pose_error(nudge @ T_true, T_true)[1] > 0.04
    assert rot < 0.3 and trans < 0.005
    assert out.rank == 6 and out.fitness > 0.5  # sparse samples: 1.5 cm gate


def test_a_corridor_keeps_the_start_along_its_axis_and_fixes_the_rest(generator):
    # two walls and a floor along y: nothing in the geometry says where along y
    corridor = [([-1.0, -4.0, 0.0], [-1.0, 4.0, 2.0]), ([1.0, -4.0, 0.0], [1.0, 4.0, 2.0])]
    corridor.append(([-1.0, -4.0, 0.0], [1.0, 4.0, 0.0]))
    tgt = _boxes(60_000, corridor, generator)
    src = _boxes(60_000, corridor, generator)
    start = torch.eye(4, dtype=torch.float64)
    start[:3, 3] = torch.tensor([0.04, 0.30, -0.03])
    out = refine_multiscale(src, tgt, start, voxel_size=0.025)
    assert out.T_tgt_src[1, 3] == pytest.approx(0.30, abs=0.01)  # held
    assert abs(float(out.T_tgt_src[0, 3])) < 0.005 and abs(float(out.T_tgt_src[2, 3])) < 0.005
    assert out.rank == 5


def test_too_few_points_return_the_start():
    pts = torch.rand(4, 3, dtype=torch.float64)
    start = torch.eye(4, dtype=torch.float64)
    start[0, 3] = 0.1
    out = refine_multiscale(pts, pts, start, voxel_size=0.025)
    assert torch.equal(out.T_tgt_src, start)


def test_prepared_clouds_give_the_same_result_and_check_the_voxel(generator):
    tgt = _boxes(20_000, ROOM, generator)
    src = _boxes(20_000, ROOM, generator)
    start = torch.eye(4, dtype=torch.float64)
    start[:3, 3] = torch.tensor([0.03, -0.02, 0.01])
    direct = refine_multiscale(src, tgt, start, voxel_size=0.025)
    prepared = RefineCloud(src, 0.025), RefineCloud(tgt.numpy(), 0.025)
    for _ in range(2):  # the second run uses the levels the first one built
        again = refine_multiscale(*prepared, start, voxel_size=0.025)
        assert torch.equal(again.T_tgt_src, direct.T_tgt_src) and again.rank == direct.rank
    with pytest.raises(ValueError, match="voxel"):
        refine_multiscale(prepared[0], prepared[1], start, voxel_size=0.05)


def test_georeferenced_coordinates_refine_as_well_as_near_the_origin(generator):
    # UTM-like coordinates (hundreds of km): the grids start at the cloud, not at 0
    T_true = _motion([0.0, 0.1, -0.2], [0.1, -0.1, 0.05])
    src, tgt = _room_pair(40_000, T_true, generator)
    nudge = _motion([0.0, math.radians(2.0), 0.0], [0.03, 0.02, -0.01])
    near = refine_multiscale(src, tgt, nudge @ T_true, voxel_size=0.025)
    offset = torch.tensor([512_345.0, 4_123_456.0, 310.0], dtype=torch.float64)
    shift = make_transform(torch.eye(3, dtype=torch.float64), offset)
    far = refine_multiscale(
        src + offset,
        tgt + offset,
        shift @ nudge @ T_true @ invert_transform(shift),
        voxel_size=0.025,
    )
    back = invert_transform(shift) @ far.T_tgt_src @ shift
    assert _pose_error(near.T_tgt_src, T_true)[1] < 0.005
    rot, trans = _pose_error(back, near.T_tgt_src)
    assert rot < 0.05 and trans < 0.001


def test_searches_side_by_side_give_the_same_bytes(generator, monkeypatch):
    T_true = _motion([0.05, -0.1, 0.2], [0.1, 0.05, -0.05])
    src, tgt = _room_pair(30_000, T_true, generator)
    start = _motion([0.0, 0.02, 0.0], [0.03, -0.02, 0.01]) @ T_true
    alone = refine_multiscale(src, tgt, start, voxel_size=0.025)
    halves = []

    def counted(calls):
        halves.append(len(calls))
        return side_by_side(pool)(calls)

    monkeypatch.setattr(refine_module, "SPLIT_SEARCH", 64)  # every level's search split
    pool = worker_pool(2)
    try:
        split = refine_multiscale(src, tgt, start, voxel_size=0.025, parallel=counted)
    finally:
        pool.shutdown()
    assert halves and set(halves) == {2}
    assert torch.equal(split.T_tgt_src, alone.T_tgt_src)
    assert (split.rank, split.fitness, split.rmse) == (alone.rank, alone.fitness, alone.rmse)
    assert split.conditioning == alone.conditioning


def test_a_pair_refinement_reports_fitness_rmse_and_the_information_of_open3d(generator):
    o3d = pytest.importorskip("open3d")
    import numpy as np

    T_true = _motion([0.02, -0.03, 0.04], [0.03, -0.02, 0.01])
    src, tgt = _room_pair(30000, T_true, generator)
    a, b = refine_pairs.pair_cloud(src, 0.02), refine_pairs.pair_cloud(tgt, 0.02)
    assert refine_pairs.icp_voxel(a) == pytest.approx(0.02)
    assert refine_pairs.enough_points(a) and refine_pairs.enough_points(b)
    fit = refine_pairs.refine_pair(a, b, np.eye(4))
    rot, trans = _pose_error(torch.from_numpy(fit.T_tgt_src), T_true)
    assert rot < 0.5 and trans < 0.005
    assert fit.fitness > 0.5 and 0 < fit.rmse < 0.02  # metres (sparse samples: a 3 cm gate)
    # the information matrix Open3D's pose graph reads, computed on the same finest points
    level = len(a.levels) - 1
    pcd_a = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(a.source(level).numpy()))
    pcd_b = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b.target(level)[0].numpy()))
    distance = refine_pairs.FINE_DISTANCE * 0.02
    theirs = o3d.pipelines.registration.get_information_matrix_from_point_clouds(
        pcd_a, pcd_b, distance, fit.T_tgt_src
    )
    theirs = np.asarray(theirs)
    assert np.linalg.norm(fit.information - theirs) < 1e-3 * np.linalg.norm(theirs)
    # a cloud without points at a level is not enough for a pair
    assert not refine_pairs.enough_points(refine_pairs.pair_cloud(src[:5], 0.02))


def test_a_pyramid_cloud_averages_its_coarse_levels_from_the_finest(generator):
    src = _boxes(20000, ROOM, generator)
    exact, pyramid = RefineCloud(src, 0.1), RefineCloud(src, 0.1, pyramid=True)
    finest = len(exact.levels) - 1
    assert torch.equal(pyramid.average(finest), exact.average(finest))
    for level in range(finest):
        a, b = exact.average(level), pyramid.average(level)
        # the same surfaces: the pyramid's averages lie near the exact averages of its level
        size = exact.levels[level][0]
        d = torch.cdist(b, a).min(dim=1).values
        assert abs(len(a) - len(b)) <= 0.1 * len(a) and float(d.median()) < 0.1 * size
    assert refine_pairs.pair_cloud(src, 0.02).pyramid


def test_a_pair_cloud_that_drops_its_points_refines_the_same(generator):
    import numpy as np

    T_true = _motion([0.02, -0.03, 0.04], [0.03, -0.02, 0.01])
    src, tgt = _room_pair(20000, T_true, generator)
    kept = refine_pairs.refine_pair(
        refine_pairs.pair_cloud(src, 0.02), refine_pairs.pair_cloud(tgt, 0.02), np.eye(4)
    )
    a, b = refine_pairs.pair_cloud(src, 0.02), refine_pairs.pair_cloud(tgt, 0.02)
    a.drop_points(), b.drop_points()
    assert len(a.points) < len(src)  # the finest averages in place of the points
    dropped = refine_pairs.refine_pair(a, b, np.eye(4))
    assert np.array_equal(dropped.T_tgt_src, kept.T_tgt_src)
    assert np.array_equal(dropped.information, kept.information)


def test_a_pair_refinement_measures_its_information_only_when_read(generator, monkeypatch):
    import numpy as np

    T_true = _motion([0.02, -0.03, 0.04], [0.03, -0.02, 0.01])
    src, tgt = _room_pair(20000, T_true, generator)
    a, b = refine_pairs.pair_cloud(src, 0.02), refine_pairs.pair_cloud(tgt, 0.02)
    calls = []
    measure = refine_pairs.information_matrix
    monkeypatch.setattr(
        refine_pairs, "information_matrix", lambda *args: calls.append(1) or measure(*args)
    )
    fit = refine_pairs.refine_pair(a, b, np.eye(4))
    assert calls == []
    first = fit.information
    assert calls == [1] and first.shape == (6, 6) and fit.information is first
    assert calls == [1]


def test_restarts_come_back_to_a_right_result_of_distinct_geometry(generator):
    T_true = _motion([0.1, -0.2, 0.15], [0.1, 0.2, -0.05])
    src, tgt = _room_pair(40_000, T_true, generator)
    restarts = restart_refinement(src, tgt, T_true, voxel_size=0.025)
    assert restarts.ends.shape == (7, 4, 4) and restarts.fitness.shape == (7,)
    assert restarts.returned(0) == 1.0
    assert restarts.gain(0) == -1.0  # no end elsewhere
    assert _pose_error(restarts.ends[restarts.best()], T_true)[0] < 0.5


def test_starts_refined_together_end_where_each_ends_alone(generator):
    T_true = _motion([0.1, -0.2, 0.15], [0.1, 0.2, -0.05])
    src, tgt = _room_pair(40_000, T_true, generator)
    src, tgt = RefineCloud(src, 0.025), RefineCloud(tgt, 0.025)
    centroid = src.source(0, restarts_module.RESTART_POINTS).mean(0)
    starts = restart_starts(_motion([0.05, 0.0, -0.1], [0.03, -0.02, 0.0]) @ T_true, centroid)
    starts = torch.cat([starts, _motion([0.0, 0.0, 3.0], [0.0, 0.0, 0.0])[None]])  # far off
    ends, fitness = refine_starts(src, tgt, starts, 0.025, max_source_points=2000)
    for k in range(len(starts)):
        alone = refine_multiscale(src, tgt, starts[k], 0.025, max_source_points=2000)
        assert torch.allclose(ends[k], alone.T_tgt_src, atol=1e-9)
        assert float(fitness[k]) == pytest.approx(alone.fitness, abs=1e-3)
    assert _pose_error(ends[0], T_true)[0] < 0.5


def test_restarts_on_a_sphere_find_no_basin(generator):
    # every turn about the centre fits a sphere as well: nothing brings a restart back
    points = torch.randn(20_000, 3, generator=generator, dtype=torch.float64)
    sphere = points / points.norm(dim=1, keepdim=True)
    restarts = restart_refinement(sphere, sphere.clone(), torch.eye(4, dtype=torch.float64), 0.05)
    assert restarts.returned(0) == 0.0
    assert abs(restarts.gain(0)) < 0.05


def test_restart_starts_turn_about_the_centroid():
    T = _motion([0.2, 0.1, -0.3], [1.0, -2.0, 0.5])
    centroid = torch.tensor([0.3, -0.4, 2.0], dtype=torch.float64)
    starts = restart_starts(T, centroid)
    assert torch.equal(starts[0], T)
    moved = apply_transform(starts, centroid.expand(7, 1, 3))
    assert torch.allclose(moved, apply_transform(T, centroid[None]).expand(7, 1, 3), atol=1e-12)
    for k in range(1, 7):
        assert _pose_error(starts[k], T)[0] == pytest.approx(restarts_module.RESTART_DEG)


def test_restart_bookkeeping_places_gains_and_returns():
    eye = torch.eye(4, dtype=torch.float64)
    far = _motion([0.0, 0.0, math.radians(10.0)], [0.0, 0.0, 0.0])
    near = _motion([0.0, 0.0, math.radians(0.5)], [0.01, 0.0, 0.0])
    restarts = Restarts(
        torch.stack([eye, near, far, far, near]), torch.tensor([0.5, 0.52, 0.6, 0.6, 0.5]), 0.025
    )
    assert restarts.same_place(0).tolist() == [True, True, False, False, True]
    assert restarts.best() == 2  # the first of the ties
    assert restarts.gain(0) == pytest.approx(0.1) and restarts.gain(2) == pytest.approx(-0.08)
    assert restarts.returned(0) == 0.5 and restarts.returned(2) == 0.5


def test_measure_fit_judges_a_transform_without_moving_it(generator):
    T_true = _motion([0.1, 0.3, -0.2], [0.2, -0.1, 0.05])
    src, tgt = _room_pair(60_000, T_true, generator)
    right = measure_fit(src, tgt, T_true, voxel_size=0.025)
    off = _motion([0.0, 0.0, math.radians(30.0)], [0.5, 0.0, 0.0]) @ T_true
    wrong = measure_fit(src, tgt, off, voxel_size=0.025)
    assert torch.equal(right.T_tgt_src, T_true) and torch.equal(wrong.T_tgt_src, off)
    assert right.fitness > 0.5 and right.rank == 6 and right.rmse < 0.5  # 2.5 cm sampling
    assert wrong.fitness < 0.5 * right.fitness
    # what the refinement reports at its own end, where it has converged from the truth
    refined = refine_multiscale(src, tgt, T_true, voxel_size=0.025)
    again = measure_fit(src, tgt, refined.T_tgt_src, voxel_size=0.025)
    assert again.fitness == pytest.approx(refined.fitness, abs=0.01)


def test_measure_fit_of_clouds_that_do_not_meet_is_zero():
    a = torch.rand(500, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    out = measure_fit(a, a + 100.0, torch.eye(4, dtype=torch.float64), voxel_size=0.025)
    assert out.fitness == 0.0 and out.rank == 0


def test_the_steps_nearest_points_are_those_of_the_cell_index(generator):
    """The refinement's numpy nearest-of-candidates against the cell index's (torch): the
    same points and the same float32 distances."""
    from byoc_cli.geometry.neighbors import (
        CellIndex,
        candidate_coordinates,
        nearest_candidates,
        nearest_of,
        nearest_of_arrays,
    )

    target = _boxes(4000, ROOM, generator)
    index = CellIndex(target, 0.05, 1)
    queries = _boxes(500, ROOM, generator) + 0.01 * torch.randn(
        500, 3, generator=generator, dtype=torch.float64
    )
    candidates = nearest_candidates(index, queries, 8, 1)
    coordinates = candidate_coordinates(index, candidates)
    moved = queries + 0.004  # candidates kept while the points move
    expected = nearest_of(index, moved, candidates, coordinates)
    got = nearest_of_arrays(
        moved.numpy(), index.origin.numpy(), candidates.numpy(), coordinates.numpy()
    )
    assert (got.index == expected.index.numpy()).all()
    assert (got.distance2 == expected.distance2.numpy()).all()
    assert (got.index >= 0).mean() > 0.5  # most points have a neighbour to compare


def _states(period: int, count: int, noise: float = 0.0) -> list[tuple]:
    """``count`` steps whose poses go round a cycle of ``period`` after two lead-in steps,
    each with its step number as the fitness (to tell which entry was taken)."""
    import numpy as np

    poses = [np.eye(4) + 0.01 * k for k in range(period)]
    out = []
    for n in range(count):
        T = np.eye(4) * 5.0 if n < 2 else poses[(n - 2) % period] + noise * n
        out.append((T, float(n), 0.1, 6, 0.5))
    return out


@pytest.mark.parametrize("period", [2, 3, 4, 5, 6])
def test_a_cycle_of_steps_is_found_once_it_closes_and_not_across_a_search(period):
    closed = _states(period, 2 + period + 1)  # the last step ends where `period` before it did
    assert refine_module.cycle_period(closed, unsearched=period - 1) == period
    assert refine_module.cycle_period(closed, unsearched=period - 2) == 0  # a search inside it
    assert refine_module.cycle_period(closed[:-1], unsearched=10) == 0  # not closed yet
    drifting = _states(period, 2 + period + 1, noise=1e-9)  # moves more than rounding
    assert refine_module.cycle_period(drifting, unsearched=10) == 0


@pytest.mark.parametrize("period", [2, 3, 4, 5, 6])
@pytest.mark.parametrize("iterations", [12, 13, 29, 30])
def test_the_end_of_a_cycle_is_the_step_the_level_would_end_with(period, iterations):
    steps = _states(period, 2 + period + 1)
    every = _states(period, iterations)  # the level run out, round and round the cycle
    got = refine_module.cycle_end(steps, period, iterations)
    assert (got[0] == every[-1][0]).all()
    assert (got[1] - 2) % period == (every[-1][1] - 2) % period  # the same place in the cycle


def test_a_start_that_closes_a_cycle_stops_with_the_pose_its_level_would_end_with():
    import numpy as np

    going, cycling = 0, 1
    T = np.stack([np.eye(4), np.eye(4)])
    fitness = np.array([0.5, 0.5])
    a, b = np.eye(4) * 2.0, np.eye(4) * 3.0
    history = {going: [(np.eye(4) * 7.0, 0.1)] * 2, cycling: [(a, 0.2), (b, 0.3)]}
    T[cycling], fitness[cycling] = a, 0.4  # step 2 of its level ends where step 0 did
    searched = {going: 0, cycling: 0}
    left = restarts_module._out_of_cycles(np.array([0, 1]), T, fitness, history, 2, searched)
    assert left.tolist() == [going]
    every = [a, b] * 15  # the level run out: its step 29 (the 30th) ends at b
    assert (T[cycling] == every[refine_module.ITERATIONS - 1]).all() and fitness[cycling] == 0.3
    searched[going] = 3  # a search at this step: a cycle may not be read across it
    history[going] = [(a, 0.2), (b, 0.3)]
    T[going] = a
    assert restarts_module._out_of_cycles(
        np.array([0]), T, fitness, history, 3, searched
    ).tolist() == [going]
