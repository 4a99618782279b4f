"""The restarts after the multiscale refinement: when a restart's end replaces the result, and
the cues they leave."""

from __future__ import annotations

import math

import pytest
import torch

import byoc_cli.pipeline.register as register_module
import byoc_cli.pipeline.solve as solve_module
from byoc_cli.pipeline.refine import Refinement
from byoc_cli.pipeline.restarts import Restarts
from byoc_cli.pipeline.verdict import NO_RESTARTS


def _turn(deg: float) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    a = math.radians(deg)
    T[:2, :2] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return T


def _run(monkeypatch, fitness, ends):
    """``run_restarts`` with restarts that end at ``ends`` with ``fitness``; the start the full
    refinement was rerun from (None: not rerun) and the cues."""
    reruns = []
    monkeypatch.setattr(
        solve_module,
        "restart_refinement",
        lambda *a, **k: Restarts(torch.stack(ends), torch.tensor(fitness), 0.025),
    )

    def rerun(src, tgt, T, voxel, parallel=None):
        reruns.append(T)
        return Refinement(T, 6, 0.9, 0.2, 0.1)

    monkeypatch.setattr(solve_module, "refine_multiscale", rerun)
    first = Refinement(ends[0], 6, 0.5, 0.3, 0.1)
    refinement, cues = solve_module.run_restarts((None, None), first, 0.025, None)
    return refinement, (reruns[0] if reruns else None), cues


def test_a_better_end_elsewhere_replaces_the_result(monkeypatch):
    ends = [_turn(0), _turn(0.2), _turn(10), _turn(10.1)]
    refinement, rerun_from, cues = _run(monkeypatch, [0.50, 0.50, 0.56, 0.55], ends)
    assert torch.equal(rerun_from, ends[2]) and torch.equal(refinement.T_tgt_src, ends[2])
    # seen from the new place: the two restarts that end there of three, the old place worse
    assert cues["restart_return"] == pytest.approx(2 / 3)
    assert cues["restart_gain"] == pytest.approx(-0.06)


def test_a_slightly_better_end_elsewhere_only_lowers_the_cues(monkeypatch):
    ends = [_turn(0), _turn(0.2), _turn(10)]
    gain = solve_module.SWITCH_GAIN / 2
    refinement, rerun_from, cues = _run(monkeypatch, [0.5, 0.5, 0.5 + gain], ends)
    assert rerun_from is None and torch.equal(refinement.T_tgt_src, ends[0])
    assert cues["restart_return"] == 0.5 and cues["restart_gain"] == pytest.approx(gain)


def test_a_better_end_in_the_same_place_changes_nothing(monkeypatch):
    ends = [_turn(0), _turn(0.3), _turn(0.1)]
    refinement, rerun_from, cues = _run(monkeypatch, [0.5, 0.6, 0.55], ends)
    assert rerun_from is None and torch.equal(refinement.T_tgt_src, ends[0])
    assert cues == {"restart_return": 1.0, "restart_gain": -1.0}


def test_without_refinement_the_cues_say_no_doubt():
    from tests.pipeline.test_register_mutual import _pair

    src, tgt, T = _pair(torch.Generator().manual_seed(0))
    config = register_module.RegisterConfig(
        estimator="ransac", num_correspondences=400, max_points=0
    )
    result = register_module.estimate_transform(src, tgt, config, voxel_size=0.02)
    assert result.cues["restart_return"] == 1.0 and result.cues["restart_gain"] == -1.0
    assert torch.allclose(result.T_tgt_src, T, atol=1e-6)


def test_the_cues_without_restarts_are_the_most_confident_of_every_refined_model():
    # what lets a result below the floor skip the restarts: they could only lower it
    from byoc_cli.pipeline.confidence import MODEL_KINDS, MODELS, probability_right

    base = {
        "inlier_share": 0.2, "inlier_ratio": 0.1, "inliers": 300.0, "overlap": 0.6,
        "coarse_inlier_ratio": 0.1, "fitness": 0.5, "rmse": 0.3, "rank": 6.0,
        "conditioning": 0.05, "shift_deg": 1.0, "shift_voxels": 1.0,
    }  # fmt: skip
    for kind in MODEL_KINDS:
        best = probability_right({**base, **NO_RESTARTS}, MODELS[kind])
        for share in (0.0, 1 / 6, 0.5, 5 / 6, 1.0):
            for gain in (-1.0, -0.2, 0.0, 0.01, 0.3, 1.0):
                cues = {**base, "restart_return": share, "restart_gain": gain}
                assert probability_right(cues, MODELS[kind]) <= best + 1e-12


@pytest.mark.parametrize(("floor", "ran"), [(0.0, True), (1.0, False)])
def test_a_result_below_the_floor_skips_the_restarts(monkeypatch, floor, ran):
    from tests.pipeline.test_register_mutual import _pair

    calls = []
    restart = solve_module.run_restarts
    monkeypatch.setattr(solve_module, "run_restarts", lambda *a: calls.append(1) or restart(*a))
    src, tgt, _ = _pair(torch.Generator().manual_seed(0))
    config = register_module.RegisterConfig(
        estimator="ransac",
        num_correspondences=400,
        max_points=0,
        refine="multiscale",
        restart_floor=floor,
    )
    result = register_module.estimate_transform(src, tgt, config, voxel_size=0.2)
    assert bool(calls) == ran and ("restarts" in result.timings) == ran
    if not ran:
        assert {k: result.cues[k] for k in NO_RESTARTS} == NO_RESTARTS


def test_the_restart_floor_is_never_above_the_gate():
    from byoc_cli.pipeline.recipe import preset

    recipe = preset("byoc")
    assert register_module.register_config(recipe).restart_floor == min(
        register_module.RESTART_FLOOR, recipe.gate.min_confidence
    )
    low = recipe.changed(gate__min_confidence=0.05)
    assert register_module.register_config(low).restart_floor == 0.05
