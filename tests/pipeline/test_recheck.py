"""The check of a passing low-overlap result with another seed (pipeline/recheck.py): the rule
with stand-ins, its place in the registrar, how far apart two poses are, and a real pair
checked to the same bytes."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from byoc_cli.pipeline import recheck
from byoc_cli.pipeline.recheck import check_seed, measure, needs_check, with_check
from byoc_cli.pipeline.recipe import preset
from byoc_cli.pipeline.registrar import Registrar
from byoc_cli.pipeline.results import Registration
from byoc_cli.pipeline.retries import discounted
from tests.pipeline._clouds import cube, moved

GATE = 0.45


def _registration(confidence: float, seed: int, tx: float = 0.0, overlap=0.3) -> Registration:
    T = np.eye(4)
    T[0, 3] = tx
    return Registration(
        T, confidence, confidence >= GATE, 10, 20, 0.5, overlap, 100, 100, 0.1, 0.05, "byoc",
        "ransac", "multiscale", 1000, 100, seed, None, {"fit": 0.1},
        recipe={"seed": seed},
    )  # fmt: skip


def _apart(T_a: np.ndarray, T_b: np.ndarray) -> dict:
    """Stand-in of :func:`measure`: translation of the origin, in 0.05 m voxels."""
    gap = float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))
    return {"rotation_deg": 0.0, "translation": gap, "voxels": gap / 0.05}


class _Again:
    """A registration again with another seed: ``confidences[seed]`` at x = ``places[seed]``."""

    def __init__(self, confidences: dict[int, float], places: dict[int, float]) -> None:
        self.confidences, self.places = confidences, places
        self.seeds: list[int] = []

    def __call__(self, seed: int) -> Registration:
        self.seeds.append(seed)
        return _registration(self.confidences[seed], seed, self.places[seed])


def test_only_passing_learned_global_results_at_low_overlap_are_checked():
    ok = _registration(0.9, 0)
    assert needs_check(ok, True) and not needs_check(ok, False)
    assert not needs_check(_registration(0.3, 0), True)  # below the gate: retries, fallback
    assert not needs_check(ok._replace(features="fpfh"), True)
    assert not needs_check(ok._replace(path="local"), True)
    assert not needs_check(ok._replace(overlap=recheck.BELOW_OVERLAP), True)
    assert needs_check(ok._replace(overlap=recheck.BELOW_OVERLAP - 0.01), True)


def test_a_check_that_ends_at_the_same_place_keeps_the_result_as_it_is():
    first = _registration(0.7, 3)
    again = _Again({4: 0.9}, {4: 0.1})  # 2 voxels away: the same place
    got = with_check(first, again, 4, _apart)
    assert again.seeds == [4]
    assert got.passed and got.confidence == 0.7 and got.T_tgt_src[0, 3] == 0.0
    note = got.check
    assert note["agrees"] and not note["ambiguous"] and note["alternatives"] == []
    assert note["seed"] == 4 and note["model_confidence"] == 0.9 and note["kept_seed"] == 3
    assert note["apart"]["voxels"] == pytest.approx(2.0)
    assert got.timings["check"] == note["seconds"] >= 0 and got.timings["fit"] == 0.1


def test_a_confident_check_elsewhere_makes_the_result_ambiguous():
    first = _registration(0.7, 3)
    got = with_check(first, _Again({4: 0.5}, {4: 1.5}), 4, _apart)
    assert not got.passed and got.check["ambiguous"] and not got.check["agrees"]
    assert got.confidence == 0.7 and got.T_tgt_src[0, 3] == 0.0  # the first is more confident
    alternatives = got.check["alternatives"]
    assert [a["seed"] for a in alternatives] == [3, 4]
    assert alternatives[1]["confidence"] == pytest.approx(discounted(0.5, 2))
    assert alternatives[1]["T_tgt_src"][0][3] == 1.5


def test_the_more_confident_of_two_places_is_kept_with_the_runs_seed():
    first = _registration(0.5, 3)
    got = with_check(first, _Again({4: 0.95}, {4: 1.5}), 4, _apart)
    assert not got.passed and got.check["kept_seed"] == 4
    assert got.T_tgt_src[0, 3] == 1.5 and got.confidence == pytest.approx(discounted(0.95, 2))
    assert got.seed == 3 and got.recipe == {"seed": 3}


def test_a_check_below_the_floor_found_nothing_and_is_no_rival():
    first = _registration(0.6, 3)
    low = recheck.RIVAL_FLOOR - 0.01
    got = with_check(first, _Again({4: low}, {4: 3.0}), 4, _apart)
    assert got.passed and not got.check["agrees"] and not got.check["ambiguous"]
    got = with_check(first, _Again({4: recheck.RIVAL_FLOOR}, {4: 3.0}), 4, _apart)
    assert not got.passed


def test_the_check_seed_comes_after_the_retries():
    assert check_seed(_registration(0.9, 5), 5) == 6
    retried = _registration(0.9, 5)._replace(retries={"tries": [{}, {}]})
    assert check_seed(retried, 5) == 8
    assert check_seed(_registration(0.9, 0), 2**64 - 1) == 0


def test_two_poses_are_measured_at_the_sources_median_in_the_inputs_units():
    # a georeferenced source (kilometres out), read in millimetres (scale 0.001 to metres)
    points_mm = np.array([[4.5e8, 5.2e9, 1e5]]) + np.arange(30).reshape(10, 3)
    src = SimpleNamespace(cloud=points_mm * 0.001, points=None, scale=0.001)
    result = _registration(0.9, 0)._replace(voxel_size=0.025)  # metres: 25 mm
    T_a = np.eye(4)
    c, s = np.cos(np.radians(0.01)), np.sin(np.radians(0.01))
    T_b = np.eye(4)
    T_b[:2, :2] = [[c, -s], [s, c]]
    at = np.median(points_mm, axis=0)
    T_b[:3, 3] = at - T_b[:3, :3] @ at + [50.0, 0.0, 0.0]  # turned about the median, 50 mm off
    gap = measure(src, result)(T_b, T_a)
    assert gap["rotation_deg"] == pytest.approx(0.01, abs=1e-6)
    assert gap["translation"] == pytest.approx(50.0, rel=1e-6)
    assert gap["voxels"] == pytest.approx(2.0, rel=1e-6)


def _stand_in_registrar(monkeypatch, confidences, places, recipe=None):
    """A learned registrar whose ``match_alone`` gives ``confidences[seed]`` at
    ``places[seed]`` and whose FPFH second opinion must not run."""
    registrar = Registrar(fallback="fpfh", recipe=recipe)
    seen: list = []

    def match_alone(self, src, tgt, **kw):
        seen.append(kw["seed"])
        return _registration(confidences[kw["seed"]], kw["seed"], places[kw["seed"]])

    def second_opinion(*args):
        raise AssertionError("the fallback ran")

    monkeypatch.setattr(Registrar, "match_alone", match_alone)
    monkeypatch.setattr(registrar._fallback, "second_opinion", second_opinion)
    return registrar, seen


def _features(voxel_size: float) -> SimpleNamespace:
    return SimpleNamespace(
        voxel_size=voxel_size, cloud=None, points=np.zeros((3, 3)), scale=1.0, origin=None
    )


def test_the_registrar_checks_a_retry_that_passed_with_the_next_seed(monkeypatch):
    places = {3: 0.0, 4: 1.0, 5: 1.02}
    registrar, seen = _stand_in_registrar(monkeypatch, {3: 0.1, 4: 0.9, 5: 0.6}, places)
    own = _features(registrar.voxel_size)
    got = registrar.match(own, own, seed=3)
    assert seen == [3, 4, 5]  # the first try, a retry that passes, its check
    assert got.passed and got.check["agrees"] and got.retries["kept_seed"] == 4
    assert got.T_tgt_src[0, 3] == 1.0 and got.seed == 3

    registrar, seen = _stand_in_registrar(monkeypatch, {3: 0.9, 4: 0.6}, {3: 0.0, 4: 2.0})
    got = registrar.match(own, own, seed=3)
    assert seen == [3, 4] and got.check["ambiguous"] and not got.passed  # and no fallback


def test_no_check_without_recheck_or_at_a_scaled_voxel(monkeypatch):
    no = preset("byoc").changed(gate__recheck=False)
    registrar, seen = _stand_in_registrar(monkeypatch, {3: 0.9}, {3: 0.0}, recipe=no)
    own = _features(registrar.voxel_size)
    assert registrar.match(own, own, seed=3).check is None and seen == [3]
    registrar, seen = _stand_in_registrar(monkeypatch, {3: 0.9}, {3: 0.0})
    scaled = _features(2.1 * registrar.voxel_size)
    assert registrar.match(scaled, scaled, seed=3).check is None and seen == [3]


def test_the_presets_check_the_learned_features_only():
    assert preset("byoc").gate.recheck and not preset("fpfh").gate.recheck


@pytest.mark.slow
def test_a_real_pair_is_checked_and_kept_to_the_byte(monkeypatch):
    """The box moved: its second seed lands at the same place, and the result is the first
    try's, bytes and all, as without the check."""
    monkeypatch.setattr(recheck, "BELOW_OVERLAP", 1.01)  # the whole box overlaps
    src, (tgt, T_true) = cube(1), moved(cube(1))
    recipe = preset("byoc").changed(gate__fallback="none")
    plain = Registrar(voxel_size=0.025, recipe=recipe.changed(gate__recheck=False))
    plain = plain.register(src, tgt, seed=1)
    got = Registrar(voxel_size=0.025, recipe=recipe).register(src, tgt, seed=1)
    assert plain.check is None and plain.passed
    assert got.check["seed"] == 2 and got.check["agrees"] and got.passed
    assert got.check["apart"]["voxels"] < 1.0
    assert np.array_equal(got.T_tgt_src, plain.T_tgt_src) and got.confidence == plain.confidence
    assert np.abs(got.T_tgt_src - T_true).max() < 0.05


def test_a_check_that_cannot_fit_is_no_rival():
    from byoc_cli.errors import RegistrationError

    def again(seed: int) -> Registration:
        raise RegistrationError("only 2 correspondences (need 3)")

    first = _registration(0.7, 3)
    got = with_check(first, again, 4, _apart)
    assert got.passed and got.T_tgt_src is first.T_tgt_src and got.confidence == 0.7
    assert got.check["error"] == "only 2 correspondences (need 3)"
    assert not got.check["ambiguous"] and got.check["T_tgt_src"] is None
