"""Turned tries of the learned features (pipeline/turns.py): which result is kept, when a
result is ambiguous, and when the FPFH fallback still runs."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from byoc_cli.geometry.orientation import turn_about, up_axis
from byoc_cli.pipeline.results import Registration
from byoc_cli.pipeline.retries import discounted
from byoc_cli.pipeline.turns import (
    ALIGN_MAX_DEG,
    AUTO,
    AUTO_TURN_BELOW,
    TURN_BELOW,
    TURN_GAIN,
    TURN_ODDS,
    best_turn,
    source_turner,
    turn_starts,
    with_turns,
)
from tests.geometry.test_orientation import _planes

ROOM = _planes({0: 1500, 1: 1500, 2: 1500})  # up axis: z
GATE = 0.45


def _registration(confidence: float, tx: float = 0.0) -> Registration:
    T = np.eye(4)
    T[0, 3] = tx
    return Registration(
        T, confidence, confidence >= GATE, 10, 20, 0.5, 0.5, 100, 100, 0.1, 0.05, "byoc",
        "ransac", "multiscale", 1000, 100, 0, None, {"fit": 0.1},
    )  # fmt: skip


def _tries(by_degrees: dict[int, Registration]):
    """``turned`` and ``match`` stand-ins: a turn's features are its transform, and matching
    them gives the registration of its angle (about z, the room's up axis)."""
    seen = []

    def turned(T):
        assert abs(T[2, 2] - 1.0) < 1e-3  # turned about z
        return T

    def match(T):
        degrees = round(math.degrees(math.atan2(T[1, 0], T[0, 0]))) % 360
        seen.append(degrees)
        return by_degrees.get(degrees, _registration(0.0, 9.0 + degrees))

    return turned, match, seen


def test_a_turn_much_more_confident_replaces_the_first():
    turned, match, seen = _tries(
        {120: _registration(0.1), 180: _registration(0.9, 2.0), 240: _registration(0.2)}
    )
    got = best_turn(_registration(0.3), (ROOM, None), turned, match, GATE)
    assert sorted(seen) == [60, 120, 180, 240, 300]
    assert got.confidence == discounted(0.9, TURN_ODDS) and got.passed
    assert got.T_tgt_src[0, 3] == 2.0 and got.turns["model_confidence"] == 0.9
    assert got.turns["kept_deg"] == 180.0 and not got.turns["ambiguous"]
    assert [t["degrees"] for t in got.turns["tries"]] == [0.0, 60.0, 120.0, 180.0, 240.0, 300.0]
    assert abs(got.turns["up_axis"][2]) > 0.99
    assert "turns" in got.timings


def test_a_turn_barely_more_confident_leaves_the_first():
    small = 0.5 + TURN_GAIN / 2
    turned, match, _ = _tries({60: _registration(small, 0.01)})  # the same place
    got = best_turn(_registration(0.5), (ROOM, None), turned, match, GATE)
    assert got.confidence == 0.5 and got.turns["kept_deg"] == 0.0 and not got.turns["ambiguous"]
    assert got.passed
    turned, match, _ = _tries({60: _registration(small, 2.0)})  # as good, elsewhere
    assert best_turn(_registration(0.5), (ROOM, None), turned, match, GATE).turns["ambiguous"]


def test_two_confident_tries_that_end_apart_are_ambiguous_and_do_not_pass():
    turned, match, _ = _tries({120: _registration(0.85, 3.0), 180: _registration(0.9, 2.0)})
    got = best_turn(_registration(0.3), (ROOM, None), turned, match, GATE)
    assert got.turns["ambiguous"] and not got.passed
    assert got.confidence == discounted(0.9, TURN_ODDS)


def test_two_confident_tries_that_end_together_are_not_ambiguous():
    turned, match, _ = _tries({120: _registration(0.85, 2.01), 180: _registration(0.9, 2.0)})
    got = best_turn(_registration(0.3), (ROOM, None), turned, match, GATE)
    assert not got.turns["ambiguous"] and got.passed


def _about(T: np.ndarray, degrees: float, at: np.ndarray) -> Registration:
    """``T`` turned further by ``degrees`` about z through ``at``, as a registration."""
    got = _registration(0.85)
    return got._replace(T_tgt_src=turn_about(np.array([0.0, 0.0, 1.0]), degrees, at) @ T)


@pytest.mark.parametrize(("apart_deg", "ambiguous"), [(0.02, False), (30.0, True)])
def test_georeferenced_tries_are_compared_where_the_scan_is(apart_deg, ambiguous):
    """Tries that put a scan 500 km out at the same place are not ambiguous, though their
    translations differ by metres for 0.02 deg (and by kilometres at the origin)."""
    offset = np.array([4.5e5, 5.2e6, 100.0])
    room = np.vstack([ROOM + offset, offset + 1e6])  # and a stray point 1000 km out
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.0, 0.0]
    best = _registration(0.9)._replace(T_tgt_src=T)
    rival = _about(T, apart_deg, np.median(room, axis=0))
    turned, match, _ = _tries({120: rival, 180: best})
    got = best_turn(_registration(0.3), (room, None), turned, match, GATE)
    assert np.linalg.norm(rival.T_tgt_src[:3, 3] - T[:3, 3]) > 1.0  # far apart at the origin
    assert got.turns["kept_deg"] == 180.0 and got.turns["ambiguous"] == ambiguous
    assert got.passed != ambiguous


def test_a_rival_below_the_gate_does_not_make_a_result_ambiguous():
    turned, match, _ = _tries({120: _registration(0.44, 3.0)})  # close, elsewhere, below
    got = best_turn(_registration(0.5), (ROOM, None), turned, match, GATE)
    assert got.passed and not got.turns["ambiguous"] and got.confidence == 0.5


def test_only_a_turned_result_is_discounted_and_then_judged_again():
    turned, match, _ = _tries({180: _registration(0.6, 2.0)})  # 0.6 reads 0.43
    got = best_turn(_registration(0.2), (ROOM, None), turned, match, GATE)
    assert got.turns["kept_deg"] == 180.0 and got.turns["model_confidence"] == 0.6
    assert got.confidence == pytest.approx(0.6 / 0.4 / TURN_ODDS / (1 + 0.6 / 0.4 / TURN_ODDS))
    assert got.confidence < GATE and not got.passed
    turned, match, _ = _tries({})
    first = _registration(0.5)
    got = best_turn(first, (ROOM, None), turned, match, GATE)
    assert got.confidence == 0.5 and got.passed and got.turns["model_confidence"] == 0.5


def _made(calls, turns=True):
    def match_alone(features, tgt, **settings):
        calls.append(features)
        return features  # the stand-in features are the registrations themselves

    return SimpleNamespace(match_alone=match_alone, fallback_below=GATE, turns=turns)


@pytest.mark.parametrize(
    ("first", "turned_to", "tries", "done"),
    [
        (0.96, 0.99, 0, False),  # sure enough: no turns
        (0.3, 0.9, 5, True),  # a sure turned result: the fallback is not needed
        (0.3, 0.6, 5, False),  # not sure: the fallback still runs for a first below the gate
    ],
)
def test_with_turns_runs_them_below_its_bound_and_says_when_the_fallback_is_spared(
    first, turned_to, tries, done
):
    calls = []
    src = SimpleNamespace(cloud=ROOM, scale=1.0)
    best = _registration(turned_to, 2.0)

    def turned(T):
        return best if abs(T[0, 0] + 1) < 1e-6 else _registration(0.0, 5.0)  # the half turn

    tgt = SimpleNamespace(cloud=None)
    got, finished = with_turns(_made(calls), _registration(first), (src, tgt), turned, {})
    assert len(calls) == tries and finished == done
    assert got.confidence == (discounted(turned_to, TURN_ODDS) if tries else first)
    assert first < TURN_BELOW or got.turns is None


def test_without_a_turner_nothing_is_tried():
    calls = []
    first = _registration(0.1)
    got, finished = with_turns(
        _made(calls), first, (SimpleNamespace(cloud=ROOM, scale=1.0), None), None, {}
    )
    assert got is first and not finished and calls == []


def test_the_stand_in_reads_the_turn_back():
    T = turn_about(np.array([0.0, 0.0, 1.0]), 240.0, np.zeros(3))
    assert round(math.degrees(math.atan2(T[1, 0], T[0, 0]))) % 360 == 240


def _tilted(degrees: float) -> np.ndarray:
    """ROOM tilted by ``degrees`` about x (its up axis leaves z), about its centroid."""
    return _moved(ROOM, turn_about(np.array([1.0, 0.0, 0.0]), degrees, ROOM.mean(axis=0)))


def _moved(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def test_the_turns_are_about_the_targets_up_axis_once_the_source_is_tilted_onto_it():
    """A source camera tilted 30 deg from the target's: each start first turns the source's
    up axis onto the target's (z), then about it, and the aligned source is tried unturned."""
    source = _tilted(30.0)
    starts, report = turn_starts(source, ROOM)
    assert [deg for deg, _, _ in starts] == [0.0, 60.0, 120.0, 180.0, 240.0, 300.0]
    assert report["aligned"] and all(aligned for _, aligned, _ in starts)
    assert report["tilt_deg"] == pytest.approx(30.0, abs=2.0)
    up = up_axis(source - source.mean(axis=0))
    centre = source.mean(axis=0)
    for *_, T in starts:
        assert abs(T[:3, :3] @ up @ np.array([0.0, 0.0, 1.0])) > 0.999  # up onto z
        assert np.allclose(_moved(centre[None], T)[0], centre)  # about the source's centre
    unturned = starts[0][2]
    assert np.allclose(_moved(source, unturned), ROOM, atol=0.05)  # the tilt undone


def test_without_a_tilt_the_aligned_source_is_not_tried_unturned():
    starts, report = turn_starts(_tilted(5.0), ROOM)
    assert [deg for deg, _, _ in starts] == [60.0, 120.0, 180.0, 240.0, 300.0]
    assert report["aligned"]


def test_axes_too_far_apart_turn_the_source_about_its_own():
    source = _tilted(ALIGN_MAX_DEG + 20.0)
    starts, report = turn_starts(source, ROOM)
    assert not report["aligned"] and report["tilt_deg"] > ALIGN_MAX_DEG
    up = up_axis(source - source.mean(axis=0))
    for _, aligned, T in starts:
        assert not aligned and abs(T[:3, :3] @ up @ up) > 0.999  # about the source's own axis


def test_best_turn_reports_the_axes_and_each_tries_alignment():
    source = _tilted(30.0)
    seen = []

    def match(T):
        seen.append(T)
        return _registration(0.9 if len(seen) == 4 else 0.1, 2.0)  # the aligned 180 deg

    got = best_turn(_registration(0.2), (source, ROOM), lambda T: T, match, GATE)
    assert [t["degrees"] for t in got.turns["tries"]] == [
        0.0,
        0.0,
        60.0,
        120.0,
        180.0,
        240.0,
        300.0,
    ]
    assert [t["aligned"] for t in got.turns["tries"]] == [False] + [True] * 6
    assert got.turns["kept_deg"] == 180.0 and got.turns["model_confidence"] == 0.9
    assert got.turns["target_up_axis"][2] == pytest.approx(1.0, abs=1e-3)


def _turner_made(auto_voxel: bool, turns):
    return SimpleNamespace(
        turns=turns,
        auto_voxel=auto_voxel,
        voxel_size=0.025,
        extract_points=lambda points, scale, label, *voxel: SimpleNamespace(
            point_index=np.arange(len(points)), points=points
        ),
    )


@pytest.mark.parametrize(
    ("turns", "auto_voxel", "voxel", "tries"),
    [
        (AUTO, True, 0.025, True),  # an auto voxel that did not scale the clouds: depth frames
        (AUTO, False, 0.05, True),  # a voxel given
        (AUTO, True, 0.06, False),  # scaled: laser scans of rooms, LiDAR, objects
        (True, True, 0.06, True),  # --turns: wherever asked
        (False, True, 0.025, False),
    ],
)
def test_auto_turns_only_where_the_features_see_the_clouds_at_their_own_voxel(
    turns, auto_voxel, voxel, tries
):
    features = SimpleNamespace(cloud=ROOM, voxel_size=voxel, origin=None)
    turner = source_turner(_turner_made(auto_voxel, turns), features, 1.0, "src", (voxel,))
    assert (turner is not None) == tries


@pytest.mark.parametrize(
    ("turns", "first", "tries"), [(AUTO, 0.9, 0), (True, 0.9, 5), (AUTO, 0.8, 5)]
)
def test_the_default_turns_only_below_its_lower_bound(turns, first, tries):
    assert AUTO_TURN_BELOW < 0.9 < TURN_BELOW
    calls = []
    src, tgt = SimpleNamespace(cloud=ROOM, scale=1.0), SimpleNamespace(cloud=None)
    got, _ = with_turns(
        _made(calls, turns), _registration(first), (src, tgt), lambda T: _registration(0.0), {}
    )
    assert len(calls) == tries and got.confidence == first
