"""The structure check of a result about to pass the gate (pipeline/structure_check.py and
Solver.check_structure)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from byoc_cli.pipeline.fallback import Fallback
from byoc_cli.pipeline.recipe import preset
from byoc_cli.pipeline.register import RegisterConfig, _Timer, register_config
from byoc_cli.pipeline.solve import Solver
from byoc_cli.pipeline.structure_check import RIVAL_MARGIN, VETOED_CONFIDENCE, structure_rival
from byoc_cli.pipeline.verdict import Verdict
from tests.pipeline._rooms import SEEN_TWICE, seen_twice, turn_z

VOXEL = 0.05
TRUTH = SEEN_TWICE


@pytest.fixture(scope="module")
def clouds():
    src, tgt = seen_twice()
    return torch.from_numpy(src), torch.from_numpy(tgt)


def _rival(clouds, T: np.ndarray) -> float:
    src, tgt = clouds
    return structure_rival(src, tgt, torch.from_numpy(T), VOXEL, clouds, VOXEL)


def test_the_truth_has_no_rival_and_a_half_turn_has_one(clouds):
    assert _rival(clouds, TRUTH) < -0.3
    assert _rival(clouds, turn_z(180.0) @ TRUTH) > 0.2


def _solver(clouds, config: RegisterConfig) -> Solver:
    src, tgt = clouds
    return Solver(
        SimpleNamespace(points=src), SimpleNamespace(points=tgt), clouds, VOXEL, VOXEL, config, None
    )


def test_the_solver_caps_a_result_with_a_rival_and_keeps_one_without(clouds):
    solver = _solver(clouds, RegisterConfig())
    verdict = Verdict({"fitness": 0.9}, 0.9, 100, 0.8)
    kept = solver.check_structure(torch.from_numpy(TRUTH), verdict)
    assert kept.confidence == 0.9 and kept.cues["structure_rival"] < 0
    vetoed = solver.check_structure(torch.from_numpy(turn_z(180.0) @ TRUTH), verdict)
    assert vetoed.confidence == VETOED_CONFIDENCE
    assert vetoed.cues["structure_rival"] > 0.2
    assert vetoed.cues["fitness"] == 0.9


@pytest.mark.parametrize(
    ("rival", "capped"), [(-0.3, False), (-RIVAL_MARGIN - 0.01, False), (-0.03, True), (0.1, True)]
)
def test_a_turn_that_fits_the_clutter_as_well_makes_the_result_ambiguous(
    clouds, monkeypatch, rival, capped
):
    """A rival within RIVAL_MARGIN of the result (a room that looks the same turned) caps it
    as a better one does; NaN (no large planes) does not."""
    import byoc_cli.pipeline.solve as solve

    monkeypatch.setattr(solve, "structure_rival", lambda *a: rival)
    verdict = Verdict({"fitness": 0.9}, 0.9, 100, 0.8)
    got = _solver(clouds, RegisterConfig()).check_structure(torch.eye(4), verdict)
    assert got.confidence == (VETOED_CONFIDENCE if capped else 0.9)
    monkeypatch.setattr(solve, "structure_rival", lambda *a: float("nan"))
    unknown = _solver(clouds, RegisterConfig()).check_structure(torch.eye(4), verdict)
    assert unknown.confidence == 0.9 and np.isnan(unknown.cues["structure_rival"])


def test_a_cloud_without_large_planes_gives_no_rival():
    rng = np.random.default_rng(0)
    blob = torch.from_numpy(rng.normal(size=(3000, 3)))
    assert np.isnan(
        structure_rival(blob, blob, torch.eye(4, dtype=torch.float64), 0.1, (blob, blob), 0.1)
    )


def _solve_half_turn(clouds, turns: bool):
    """Solver.solve of exact correspondences under the half-turned truth, with the
    configuration of the byoc preset with ``turns`` (every result at the gate or above)."""
    recipe = preset("byoc").changed(matching__turns=turns)
    config = dataclasses.replace(register_config(recipe), min_confidence=0.0)
    src = clouds[0][::20]
    T = torch.from_numpy(turn_z(180.0) @ TRUTH)
    correspondences = (src, src @ T[:3, :3].T + T[:3, 3], torch.ones(len(src), dtype=src.dtype))
    timer = _Timer()
    generator = torch.Generator().manual_seed(0)
    refinement, verdict = _solver(clouds, config).solve(
        correspondences, correspondences, generator, timer
    )
    return refinement, verdict, timer.timings


def test_without_turns_the_solver_does_not_check_the_structure(clouds):
    assert not register_config(preset("byoc")).structure_check
    _, verdict, timings = _solve_half_turn(clouds, turns=False)
    assert "structure_rival" not in verdict.cues and "structure" not in timings
    assert verdict.confidence > VETOED_CONFIDENCE  # the half turn passes unchecked


def test_with_turns_the_solver_checks_and_caps_a_half_turn(clouds):
    assert register_config(preset("byoc").changed(matching__turns=True)).structure_check
    unrefined, unchecked, _ = _solve_half_turn(clouds, turns=False)
    refinement, verdict, timings = _solve_half_turn(clouds, turns=True)
    assert verdict.cues["structure_rival"] > 0.2 and "structure" in timings
    assert torch.equal(refinement.T_tgt_src, unrefined.T_tgt_src)  # only the confidence moves
    assert verdict.confidence == min(unchecked.confidence, VETOED_CONFIDENCE)


def test_the_fallback_carries_the_turns_into_its_recipe():
    assert not Fallback(0.1).registrar().recipe.matching.turns
    assert Fallback(0.1, turns=True).registrar().recipe.matching.turns
