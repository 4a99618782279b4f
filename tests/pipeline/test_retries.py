"""The retries below the gate (pipeline/retries.py): the rule with stand-ins, its place before
the FPFH fallback in the registrar, and a real pair retried to the same bytes."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from byoc_cli.pipeline.recipe import preset
from byoc_cli.pipeline.registrar import Registrar
from byoc_cli.pipeline.results import Registration
from byoc_cli.pipeline.retries import at_own_voxel, discounted, retry_seed, with_retries
from tests.pipeline._clouds import cube, moved

GATE = 0.45


def _registration(confidence: float, seed: int, tx: float = 0.0) -> Registration:
    T = np.eye(4)
    T[0, 3] = tx
    return Registration(
        T, confidence, confidence >= GATE, 10, 20, 0.5, 0.5, 100, 100, 0.1, 0.05, "byoc",
        "ransac", "multiscale", 1000, 100, seed, None, {"fit": 0.1},
        recipe={"seed": seed},
    )  # fmt: skip


class _Again:
    """A registration again with another seed: ``confidences[seed]`` at x = ``seed`` m."""

    def __init__(self, confidences: dict[int, float]) -> None:
        self.confidences = confidences
        self.seeds: list[int] = []

    def __call__(self, seed: int) -> Registration:
        self.seeds.append(seed)
        return _registration(self.confidences[seed], seed, float(seed))


def test_a_first_result_at_the_gate_or_without_retries_is_kept_untried():
    again = _Again({})
    first = _registration(GATE, 7)
    assert with_retries(first, again, 7, 2, GATE) is first
    below = _registration(0.1, 7)
    assert with_retries(below, again, 7, 0, GATE) is below
    assert again.seeds == []


def test_a_retrys_confidence_is_discounted_for_the_tries_it_was_picked_from():
    assert discounted(0.5, 1) == 0.5 and discounted(1.0, 3) == 1.0 and discounted(0.0, 3) == 0.0
    assert discounted(0.8, 2) == pytest.approx(2 / 3)  # odds 4 -> 2
    assert discounted(0.75, 3) == pytest.approx(0.5)  # odds 3 -> 1


@given(st.floats(0.0, 1.0), st.integers(1, 17))
def test_the_discount_keeps_the_order_and_never_raises(confidence, tries):
    got = discounted(confidence, tries)
    assert 0.0 <= got <= confidence
    assert discounted(min(1.0, confidence + 0.01), tries) >= got


def test_the_first_retry_that_passes_after_the_discount_replaces_the_first_result():
    again = _Again({8: 0.6, 9: 0.8, 10: 0.99})
    first = _registration(0.2, 7)
    kept = with_retries(first, again, 7, 3, GATE)
    # seed 8: 0.6 -> 0.43 below the gate (kept so far: above 0.2); seed 9: 0.8 -> 0.57 passes
    assert again.seeds == [8, 9]  # stops at the first one that passes
    assert kept.confidence == pytest.approx(discounted(0.8, 3)) and kept.passed
    assert kept.T_tgt_src[0, 3] == 9.0
    assert kept.seed == 7 and kept.recipe == {"seed": 7}  # the run's, not the retry's
    note = kept.retries
    assert note["first_confidence"] == 0.2 and note["kept_seed"] == 9
    assert [t["seed"] for t in note["tries"]] == [8, 9]
    assert [t["model_confidence"] for t in note["tries"]] == [0.6, 0.8]
    assert [t["T_tgt_src"][0][3] for t in note["tries"]] == [8.0, 9.0]  # every pose tried
    assert note["first_T_tgt_src"] == np.eye(4).tolist()
    assert note["tries"][0]["confidence"] == pytest.approx(discounted(0.6, 2))
    assert kept.timings["retries"] == note["seconds"] >= 0 and kept.timings["fit"] == 0.1


def test_the_most_confident_try_is_kept_below_the_gate_and_does_not_pass():
    """A retry that beats the first try after the discount is the answer (its T may be the
    right one), but it passes only at the gate."""
    again = _Again({8: 0.5, 9: 0.55})
    kept = with_retries(_registration(0.3, 7), again, 7, 2, GATE)
    assert again.seeds == [8, 9]
    assert kept.retries["kept_seed"] == 8  # 0.5 -> 0.333; 0.55 -> 0.290
    assert kept.confidence == pytest.approx(1 / 3) and not kept.passed
    first = _registration(0.4, 7)  # no retry beats it after the discount: the first stays
    kept = with_retries(first, _Again({8: 0.55, 9: 0.66}), 7, 2, GATE)
    assert kept.retries["kept_seed"] is None and np.array_equal(kept.T_tgt_src, first.T_tgt_src)
    assert kept.confidence == 0.4 and kept.timings["retries"] == kept.retries["seconds"]


def test_a_higher_gate_is_what_a_discounted_retry_must_reach():
    again = _Again({8: 0.9, 9: 0.97})
    kept = with_retries(_registration(0.3, 7), again, 7, 2, 0.9)
    assert again.seeds == [8, 9]  # 0.9 -> 0.82 does not pass 0.9; 0.97 -> 0.915 does
    assert kept.passed and kept.confidence == pytest.approx(discounted(0.97, 3))


def test_retry_seeds_follow_the_run_seed_and_wrap():
    assert [retry_seed(5, k) for k in (1, 2)] == [6, 7]
    assert retry_seed(2**64 - 1, 1) == 0 and retry_seed(2**64 - 1, 2) == 1
    again = _Again({0: 0.1, 1: 0.9})
    kept = with_retries(_registration(0.1, 2**64 - 1), again, 2**64 - 1, 2, GATE)
    assert again.seeds == [0, 1] and kept.retries["kept_seed"] == 1 and kept.passed


def _stand_in_registrar(monkeypatch, confidences: dict[int, float], fallback: float | None):
    """A learned registrar whose ``match_alone`` gives ``confidences[seed]`` and whose FPFH
    second opinion gives ``fallback`` (None: not expected to run)."""
    registrar = Registrar(fallback="fpfh")
    seen: list = []
    monkeypatch.setattr(
        Registrar,
        "match_alone",
        lambda self, src, tgt, **kw: (
            seen.append(kw["seed"])
            or _registration(confidences[kw["seed"]], kw["seed"], float(kw["seed"]))
        ),
    )

    def second_opinion(learned, first, src, tgt, seed):
        assert fallback is not None, "the fallback ran"
        seen.append(("fallback", first.confidence, seed))
        return first._replace(fallback={"used": False})

    monkeypatch.setattr(registrar._fallback, "second_opinion", second_opinion)
    return registrar, seen


def _features(voxel_size: float) -> SimpleNamespace:
    return SimpleNamespace(
        voxel_size=voxel_size, cloud=None, points=np.zeros((3, 3)), scale=1.0, origin=None
    )


def test_the_registrar_retries_before_the_fallback(monkeypatch):
    registrar, seen = _stand_in_registrar(monkeypatch, {3: 0.1, 4: 0.2, 5: 0.3}, 0.0)
    own = _features(registrar.voxel_size)  # the auto voxel at the features' own: retries
    got = registrar.match(own, own, seed=3)
    # no retry passed: the fallback answers to the most confident try after the discount
    # (0.3 of the third try -> 0.125), with the run's seed
    assert seen == [3, 4, 5, ("fallback", pytest.approx(0.125), 3)]
    assert got.retries["kept_seed"] == 5 and got.confidence == pytest.approx(0.125)

    registrar, seen = _stand_in_registrar(monkeypatch, {3: 0.1, 4: 0.8}, None)
    got = registrar.match(own, own, seed=3)
    assert seen == [3, 4]  # 0.8 -> 0.667 passes: no fallback
    assert got.retries["kept_seed"] == 4 and got.T_tgt_src[0, 3] == 4.0 and got.seed == 3


def test_clouds_brought_to_the_features_scale_are_not_retried(monkeypatch):
    registrar, seen = _stand_in_registrar(monkeypatch, {3: 0.1, 4: 0.9}, 0.0)
    scaled = _features(2.1 * registrar.voxel_size)  # a room scanned by a TLS, say
    got = registrar.match(scaled, scaled, seed=3)
    assert seen == [3, ("fallback", 0.1, 3)] and got.retries is None
    assert at_own_voxel(registrar, _features(registrar.voxel_size))
    with pytest.warns(UserWarning, match="differs from the 0.025 m"):  # said, not refused
        given = Registrar(fallback="fpfh", voxel_size=0.05)  # a voxel given: always its own
    assert at_own_voxel(given, _features(0.05))


def test_the_presets_retry_the_learned_features_only():
    assert preset("byoc").gate.retries == 2
    assert preset("fpfh").gate.retries == 0


@pytest.mark.slow
def test_a_real_pair_below_the_gate_is_retried_and_the_first_try_kept_to_the_byte():
    """With the gate at 1.0 no try is sure: two retries run (seeds 2 and 3) and the result is
    the first try's, bytes and all, as without retries."""
    src, (tgt, _) = cube(1), moved(cube(1))
    recipe = preset("byoc").changed(gate__min_confidence=1.0, gate__fallback="none")
    voxel = 0.025  # a voxel given: the features' own (the auto one scales a 3 m box)
    plain = Registrar(voxel_size=voxel, recipe=recipe.changed(gate__retries=0))
    plain = plain.register(src, tgt, seed=1)
    retried = Registrar(voxel_size=voxel, recipe=recipe).register(src, tgt, seed=1)
    assert plain.retries is None
    assert [t["seed"] for t in retried.retries["tries"]] == [2, 3]
    assert retried.retries["kept_seed"] is None
    assert retried.retries["first_confidence"] == plain.confidence
    assert retried.retries["first_T_tgt_src"] == plain.T_tgt_src.tolist()
    assert np.array_equal(retried.T_tgt_src, plain.T_tgt_src)
    assert retried.confidence == plain.confidence and not retried.passed


@pytest.mark.slow
def test_the_report_keeps_the_retries_whichever_result_the_fallback_keeps():
    src, (tgt, _) = cube(1), moved(cube(1))
    recipe = preset("byoc").changed(gate__min_confidence=1.0)  # every try below: all run
    got = Registrar(voxel_size=0.025, recipe=recipe).register(src, tgt, seed=1)
    assert got.fallback["learned_confidence"] == got.retries["first_confidence"]
    assert len(got.retries["tries"]) == 2 and got.retries["kept_seed"] is None
    assert got.timings["retries"] == got.retries["seconds"] and "fallback" in got.timings


def test_a_retry_that_cannot_fit_is_listed_and_the_next_seed_tried():
    from byoc_cli.errors import RegistrationError

    def again(seed: int) -> Registration:
        if seed == 8:
            raise RegistrationError("only 2 correspondences (need 3)")
        return _registration(0.9, seed, float(seed))

    kept = with_retries(_registration(0.1, 7), again, 7, 2, GATE)
    assert kept.retries["tries"][0] == {
        "seed": 8, "confidence": None, "error": "only 2 correspondences (need 3)"
    }  # fmt: skip
    assert kept.retries["kept_seed"] == 9 and kept.T_tgt_src[0, 3] == 9.0
    assert kept.confidence == pytest.approx(discounted(0.9, 3)) and kept.passed
