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
from byoc_cli.pipeline.structure_check import (
    ADOPT_GAIN,
    RIVAL_MARGIN,
    VETOED_CONFIDENCE,
    Rival,
    RivalCheck,
    structure_rival,
)
from byoc_cli.pipeline.verdict import Verdict
from tests._rings import room_scan
from tests.pipeline._rooms import SEEN_TWICE, seen_twice, turn_z

VOXEL = 0.05
TRUTH = SEEN_TWICE


@pytest.fixture(scope="module")
def clouds():
    src, tgt = seen_twice()
    return torch.from_numpy(src), torch.from_numpy(tgt)


def _rival(clouds, T: np.ndarray) -> Rival:
    src, tgt = clouds
    return structure_rival(src, tgt, torch.from_numpy(T), VOXEL, clouds, VOXEL)


def test_the_occupancy_starts_give_the_same_rivals_here(clouds):
    """With ``correlate`` (rooms) each turn starts twice; on this room both find the truth."""
    src, tgt = clouds
    check = RivalCheck(src, tgt, VOXEL, clouds, VOXEL)
    rival = check(torch.from_numpy(turn_z(180.0) @ TRUTH), correlate=True)
    assert rival.gain > 0.2 and np.abs(rival.T_tgt_src - TRUTH).max() < VOXEL / 5
    assert check(torch.from_numpy(TRUTH), correlate=True).gain < -0.3


def test_a_room_is_mostly_large_planes_and_an_object_is_not():
    """RivalCheck.room_like: an empty room's scan lies on its planes; a blob centred on its
    origin (an object, in millimetres a panorama as large as a room) has none."""
    room = torch.from_numpy(room_scan(2.0))
    assert RivalCheck(room, room, 0.1, (room, room), 0.1).room_like
    rng = np.random.default_rng(0)
    blob = rng.normal(size=(3000, 3))
    blob = torch.from_numpy(100.0 * blob / np.linalg.norm(blob, axis=1, keepdims=True))
    assert not RivalCheck(blob, blob, 5.0, (blob, blob), 5.0).room_like


def test_a_turn_refined_back_onto_the_result_is_no_rival(clouds, monkeypatch):
    """A smooth object's turned starts come back to the result: no rival (NaN), not one that
    fits as well."""
    import byoc_cli.pipeline.structure_check as structure_check

    src, tgt = clouds
    monkeypatch.setattr(
        structure_check,
        "refine_starts",
        lambda *a, **k: (torch.from_numpy(np.stack([TRUTH] * 3)), None),
    )
    rival = RivalCheck(src, tgt, VOXEL, clouds, VOXEL)(torch.from_numpy(TRUTH))
    assert np.isnan(rival.gain) and rival.T_tgt_src is None


def test_the_truth_has_no_rival_and_a_half_turn_has_the_truth_for_one(clouds):
    assert _rival(clouds, TRUTH).gain < -0.3
    rival = _rival(clouds, turn_z(180.0) @ TRUTH)
    assert rival.gain > 0.2
    assert np.abs(rival.T_tgt_src - TRUTH).max() < VOXEL / 5  # refined onto the truth


@pytest.mark.parametrize("degrees", [90.0, 270.0])
def test_a_quarter_turn_has_the_truth_for_a_rival(clouds, degrees):
    rival = _rival(clouds, turn_z(degrees) @ TRUTH)
    assert rival.gain > ADOPT_GAIN
    assert np.abs(rival.T_tgt_src - TRUTH).max() < VOXEL / 5


def _solver(clouds, config: RegisterConfig) -> Solver:
    src, tgt = clouds
    return Solver(
        SimpleNamespace(points=src), SimpleNamespace(points=tgt), clouds, VOXEL, VOXEL, config, None
    )


class _Judge:
    """A stand-in judge: the verdict of a refinement is its fitness, at confidence 0.7."""

    def __call__(self, refinement, restart_cues):
        return Verdict({"fitness": refinement.fitness}, 0.7, 50, 0.6)


def _refinement(T: np.ndarray):
    return SimpleNamespace(T_tgt_src=torch.from_numpy(T), fitness=0.9)


ROOMS = RegisterConfig(turn_rooms=True)
TURNS = RegisterConfig(structure_check=True)  # --turns


def test_the_solver_keeps_a_result_without_a_rival_and_on_rooms_adopts_a_better_one(clouds):
    solver = _solver(clouds, ROOMS)
    verdict = Verdict({"fitness": 0.9}, 0.9, 100, 0.8)
    refinement, kept = solver.check_structure(_refinement(TRUTH), verdict, _Judge())
    assert kept.confidence == 0.9 and kept.cues["structure_rival"] < 0
    assert "structure_adopted" not in kept.cues
    assert torch.equal(refinement.T_tgt_src, torch.from_numpy(TRUTH))
    half = turn_z(180.0) @ TRUTH
    refinement, adopted = solver.check_structure(_refinement(half), verdict, _Judge())
    assert np.abs(refinement.T_tgt_src.numpy() - TRUTH).max() < VOXEL / 5
    assert adopted.cues["structure_adopted"] > 0.2  # the half turn's rival, the truth
    assert adopted.cues["structure_rival"] < -0.3  # the truth's own rivals fit worse
    assert adopted.confidence == 0.7  # the judge's verdict on the adopted result
    assert adopted.cues["fitness"] == pytest.approx(refinement.fitness)
    # elsewhere (--turns on depth frames) a better rival vetoes the result, never replaces it
    refinement, vetoed = _solver(clouds, TURNS).check_structure(
        _refinement(half), verdict, _Judge()
    )
    assert torch.equal(refinement.T_tgt_src, torch.from_numpy(half))
    assert vetoed.confidence == VETOED_CONFIDENCE and "structure_adopted" not in vetoed.cues


def _stand_in(rival, room_like: bool = True):
    """A RivalCheck class whose checks return ``rival()``."""

    class StandIn:
        def __init__(self, *args, **kwargs):
            self.room_like = room_like

        def __call__(self, T, correlate=False):
            return rival()

    return StandIn


def test_a_large_panorama_that_is_no_room_is_left_unchecked(clouds, monkeypatch):
    """turn_rooms on an object centred on its origin: no check, unless --turns asks."""
    import byoc_cli.pipeline.solve as solve

    monkeypatch.setattr(solve, "RivalCheck", _stand_in(lambda: Rival(0.3, TRUTH), False))
    verdict = Verdict({"fitness": 0.9}, 0.9, 100, 0.8)
    half = _refinement(turn_z(180.0) @ TRUTH)
    refinement, got = _solver(clouds, ROOMS).check_structure(half, verdict, _Judge())
    assert got is verdict and refinement is half
    config = RegisterConfig(turn_rooms=True, structure_check=True)
    refinement, vetoed = _solver(clouds, config).check_structure(half, verdict, _Judge())
    assert vetoed.confidence == VETOED_CONFIDENCE and refinement is half  # not adopted


@pytest.mark.parametrize(
    ("gain", "capped"), [(-0.3, False), (-RIVAL_MARGIN - 0.01, False), (-0.03, True), (0.05, True)]
)
def test_a_turn_that_fits_the_clutter_as_well_makes_the_result_ambiguous(
    clouds, monkeypatch, gain, capped
):
    """A rival within RIVAL_MARGIN of the result (a room that looks the same turned) caps it
    as a better one below ADOPT_GAIN does; NaN (no large planes) does not."""
    import byoc_cli.pipeline.solve as solve

    monkeypatch.setattr(solve, "RivalCheck", _stand_in(lambda: Rival(gain, np.eye(4))))
    verdict = Verdict({"fitness": 0.9}, 0.9, 100, 0.8)
    _, got = _solver(clouds, TURNS).check_structure(_refinement(np.eye(4)), verdict, _Judge())
    assert got.confidence == (VETOED_CONFIDENCE if capped else 0.9)
    monkeypatch.setattr(solve, "RivalCheck", _stand_in(lambda: Rival(float("nan"), None)))
    _, unknown = _solver(clouds, TURNS).check_structure(_refinement(np.eye(4)), verdict, _Judge())
    assert unknown.confidence == 0.9 and np.isnan(unknown.cues["structure_rival"])


def test_an_adopted_rival_that_has_a_rival_of_its_own_is_ambiguous(clouds, monkeypatch):
    """A point-symmetric room: the rival adopted fits its own half turn as well."""
    import byoc_cli.pipeline.solve as solve

    gains = iter([0.3, -0.01])
    monkeypatch.setattr(solve, "RivalCheck", _stand_in(lambda: Rival(next(gains), TRUTH)))
    verdict = Verdict({"fitness": 0.9}, 0.9, 100, 0.8)
    _, got = _solver(clouds, ROOMS).check_structure(
        _refinement(turn_z(180.0) @ TRUTH), verdict, _Judge()
    )
    assert got.cues["structure_adopted"] == 0.3 and got.cues["structure_rival"] == -0.01
    assert got.confidence == VETOED_CONFIDENCE


def test_a_cloud_without_large_planes_gives_no_rival():
    rng = np.random.default_rng(0)
    blob = torch.from_numpy(rng.normal(size=(3000, 3)))
    rival = structure_rival(blob, blob, torch.eye(4, dtype=torch.float64), 0.1, (blob, blob), 0.1)
    assert np.isnan(rival.gain) and rival.T_tgt_src is None


def _solve_half_turn(clouds, turns: bool, rooms: bool = False):
    """Solver.solve of exact correspondences under the half-turned truth, with the
    configuration of the byoc preset with ``turns`` (every result at the gate or above) and
    ``rooms`` (``turn_rooms``)."""
    recipe = preset("byoc").changed(matching__turns=turns)
    config = register_config(recipe)
    config = dataclasses.replace(config, min_confidence=0.0, turn_rooms=rooms)
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


def test_on_rooms_the_solver_adopts_the_truth_over_a_half_turn(clouds):
    unrefined, _, _ = _solve_half_turn(clouds, turns=False)
    refinement, verdict, timings = _solve_half_turn(clouds, turns=True, rooms=True)
    assert np.abs(unrefined.T_tgt_src.numpy() - turn_z(180.0) @ TRUTH).max() < VOXEL / 5
    assert np.abs(refinement.T_tgt_src.numpy() - TRUTH).max() < VOXEL / 5
    assert verdict.cues["structure_adopted"] > 0.2 and "structure" in timings
    assert verdict.cues["structure_rival"] < -0.3


def test_the_fallback_carries_the_turns_into_its_recipe():
    assert not Fallback(0.1).registrar().recipe.matching.turns
    assert Fallback(0.1, turns=True).registrar().recipe.matching.turns
