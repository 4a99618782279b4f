"""register_scans_from_poses: recovery from perturbed poses, the init deciding a symmetric
scene, the trust region, the pairs chosen by the poses' overlap."""

from __future__ import annotations

import numpy as np
import pytest

from byoc_cli.errors import ShapeError
from byoc_cli.pipeline.local import TrustRegion
from byoc_cli.pipeline.posegraph import transform_difference
from byoc_cli.pipeline.scans_init import register_scans_from_poses
from tests.pipeline import _rooms as rooms


@pytest.fixture(scope="module")
def room():
    return rooms.scans()


def test_poses_8_deg_and_20_cm_off_come_back_to_the_truth(room):
    guesses = rooms.guesses(8.0, 0.2)  # in a world of their own: only relative poses count
    result = register_scans_from_poses(room, guesses)
    assert result.unplaced == []
    for pose, truth in zip(result.poses, rooms.STATIONS, strict=True):
        degrees, metres = transform_difference(truth, pose)
        assert degrees < 0.1 and metres < 0.003, (degrees, metres)  # measured 0.008, 0.0001
    np.testing.assert_array_equal(result.poses[0], np.eye(4))
    assert {(p.i, p.j) for p in result.pairs} == {(0, 1), (0, 2), (1, 2)}
    assert all(p.kind == "overlap" and p.status == "kept" for p in result.pairs)
    first = next(p for p in result.pairs if (p.i, p.j) == (0, 1))
    assert first.init["inside_trust_region"]
    assert first.init["correction"]["rotation_deg"] == pytest.approx(8.0, abs=0.1)
    assert result.timings["features"] == 0.0


@pytest.mark.parametrize("flipped", [False, True], ids=["truth", "half-turn"])
def test_in_a_symmetric_room_the_initial_poses_decide(flipped):
    # a half turn about the room's vertical axis maps it onto itself: the data fit scan 1
    # at its true pose and at the true pose followed by that half turn equally well
    clouds = rooms.scans(rooms.SYMMETRIC, rooms.STATIONS[:2])
    half = rooms.turn_z(180.0)
    truth = rooms.STATIONS[1] if not flipped else half @ rooms.STATIONS[1]
    rng = np.random.default_rng(1)
    guess = rooms.perturbed(truth, 8.0, 0.15, rng)
    result = register_scans_from_poses(clouds, [np.eye(4), guess])
    degrees, metres = transform_difference(truth, result.poses[1])
    assert degrees < 0.2 and metres < 0.005, (degrees, metres)


def test_a_pair_that_leaves_the_trust_region_is_no_edge(room):
    guesses = rooms.guesses(8.0, 0.2)
    result = register_scans_from_poses(room, guesses, trust=TrustRegion(3.0))
    assert result.unplaced == [1, 2] and result.poses[1] is None
    assert all(p.status == "rejected" and p.edge == "" for p in result.pairs)
    assert not any(p.init["inside_trust_region"] for p in result.pairs)
    # the fit was right all the same: it is the bound that rejects it
    assert all(p.fitness > 0.7 for p in result.pairs)


def test_pairs_are_the_ones_that_overlap_under_the_poses(room):
    guesses = rooms.guesses(2.0, 0.05)
    guesses[2] = guesses[2] @ rooms.turn_z(0.0, (40.0, 0.0, 0.0))  # scan 2 put 40 m away
    result = register_scans_from_poses(room, guesses)
    assert [(p.i, p.j) for p in result.pairs] == [(0, 1)]
    assert result.unplaced == [2]


def test_one_finite_pose_per_cloud(room):
    with pytest.raises(ShapeError, match="one finite"):
        register_scans_from_poses(room, rooms.STATIONS[:2])
    bad = [p.copy() for p in rooms.STATIONS]
    bad[1][0, 3] = np.nan
    with pytest.raises(ShapeError):
        register_scans_from_poses(room, bad)
