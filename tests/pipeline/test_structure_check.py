"""The structure check of a result about to pass the gate (pipeline/structure_check.py and
Solver.check_structure)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from byoc_cli.pipeline.register import RegisterConfig
from byoc_cli.pipeline.solve import Solver
from byoc_cli.pipeline.structure_check import RIVAL_GAIN, VETOED_CONFIDENCE, structure_rival
from byoc_cli.pipeline.verdict import Verdict
from tests.pipeline._rooms import ROOM, scans, turn_z

VOXEL = 0.05
TRUTH = turn_z(30.0, (0.2, -0.1, 0.0))


@pytest.fixture(scope="module")
def clouds():
    src = scans(ROOM, [np.eye(4), TRUTH], n=6000)[1]
    tgt = scans(ROOM, [np.eye(4)], n=6000, seed=5)[0]
    return torch.from_numpy(src), torch.from_numpy(tgt)


def _rival(clouds, T: np.ndarray) -> float:
    src, tgt = clouds
    return structure_rival(src, tgt, torch.from_numpy(T), VOXEL, clouds, VOXEL)


def test_the_truth_has_no_rival_and_a_half_turn_has_one(clouds):
    assert _rival(clouds, TRUTH) < -0.3
    assert _rival(clouds, turn_z(180.0) @ TRUTH) > RIVAL_GAIN


def test_the_solver_caps_a_result_with_a_rival_and_keeps_one_without(clouds):
    src, tgt = clouds
    solver = Solver(
        SimpleNamespace(points=src),
        SimpleNamespace(points=tgt),
        clouds,
        VOXEL,
        VOXEL,
        RegisterConfig(),
        None,
    )
    verdict = Verdict({"fitness": 0.9}, 0.9, 100, 0.8)
    kept = solver.check_structure(torch.from_numpy(TRUTH), verdict)
    assert kept.confidence == 0.9 and kept.cues["structure_rival"] < 0
    vetoed = solver.check_structure(torch.from_numpy(turn_z(180.0) @ TRUTH), verdict)
    assert vetoed.confidence == VETOED_CONFIDENCE
    assert vetoed.cues["structure_rival"] > RIVAL_GAIN
    assert vetoed.cues["fitness"] == 0.9


def test_a_cloud_without_large_planes_gives_no_rival():
    rng = np.random.default_rng(0)
    blob = torch.from_numpy(rng.normal(size=(3000, 3)))
    assert np.isnan(
        structure_rival(blob, blob, torch.eye(4, dtype=torch.float64), 0.1, (blob, blob), 0.1)
    )
