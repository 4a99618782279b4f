"""Turned tries of the learned features (pipeline/turns.py): which result is kept, when a
result is ambiguous, and when the FPFH fallback still runs."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from byoc_cli.geometry.orientation import turn_about
from byoc_cli.pipeline.results import Registration
from byoc_cli.pipeline.turns import TURN_BELOW, TURN_GAIN, best_turn, with_turns
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
    got = best_turn(_registration(0.3), ROOM, turned, match, GATE)
    assert sorted(seen) == [60, 120, 180, 240, 300]
    assert got.confidence == 0.9 and got.passed and got.T_tgt_src[0, 3] == 2.0
    assert got.turns["kept_deg"] == 180.0 and not got.turns["ambiguous"]
    assert [t["degrees"] for t in got.turns["tries"]] == [0.0, 60.0, 120.0, 180.0, 240.0, 300.0]
    assert abs(got.turns["up_axis"][2]) > 0.99
    assert "turns" in got.timings


def test_a_turn_barely_more_confident_leaves_the_first():
    small = 0.5 + TURN_GAIN / 2
    turned, match, _ = _tries({60: _registration(small, 0.01)})  # the same place
    got = best_turn(_registration(0.5), ROOM, turned, match, GATE)
    assert got.confidence == 0.5 and got.turns["kept_deg"] == 0.0 and not got.turns["ambiguous"]
    assert got.passed
    turned, match, _ = _tries({60: _registration(small, 2.0)})  # as good, elsewhere
    assert best_turn(_registration(0.5), ROOM, turned, match, GATE).turns["ambiguous"]


def test_two_confident_tries_that_end_apart_are_ambiguous_and_do_not_pass():
    turned, match, _ = _tries({120: _registration(0.85, 3.0), 180: _registration(0.9, 2.0)})
    got = best_turn(_registration(0.3), ROOM, turned, match, GATE)
    assert got.turns["ambiguous"] and not got.passed and got.confidence == 0.9


def test_two_confident_tries_that_end_together_are_not_ambiguous():
    turned, match, _ = _tries({120: _registration(0.85, 2.01), 180: _registration(0.9, 2.0)})
    got = best_turn(_registration(0.3), ROOM, turned, match, GATE)
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
    got = best_turn(_registration(0.3), room, turned, match, GATE)
    assert np.linalg.norm(rival.T_tgt_src[:3, 3] - T[:3, 3]) > 1.0  # far apart at the origin
    assert got.turns["kept_deg"] == 180.0 and got.turns["ambiguous"] == ambiguous
    assert got.passed != ambiguous


def test_a_rival_below_the_gate_does_not_make_a_result_ambiguous():
    turned, match, _ = _tries({120: _registration(0.4, 3.0), 180: _registration(0.46, 2.0)})
    got = best_turn(_registration(0.0), ROOM, turned, match, GATE)
    assert got.passed and not got.turns["ambiguous"]


def _made(calls):
    def match_alone(features, tgt, **settings):
        calls.append(features)
        return features  # the stand-in features are the registrations themselves

    return SimpleNamespace(match_alone=match_alone, fallback_below=GATE)


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

    got, finished = with_turns(_made(calls), _registration(first), (src, None), turned, {})
    assert len(calls) == tries and finished == done
    assert got.confidence == (turned_to if tries else first)
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
