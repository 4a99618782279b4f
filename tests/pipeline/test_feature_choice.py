"""Which features a pair starts with: the rule by hand, FPFH first, its repeats and the learned
features as its second opinion with stand-ins, and the whole engine on a smooth and a
cluttered pair."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from byoc_cli.errors import RegistrationError
from byoc_cli.geometry.transforms import axis_angle_matrix
from byoc_cli.pipeline.feature_choice import (
    AGREE_DEG,
    AGREE_VOXELS,
    COARSER,
    COARSER_RMSE,
    REPRODUCE_RMSE,
    REPRODUCED_CONFIDENCE,
    SMOOTH_FPFH,
    SMOOTH_SHARE,
    applies,
    choose_features,
    features_for,
    smooth_first,
)
from byoc_cli.pipeline.local import correction
from byoc_cli.pipeline.results import Registration
from tests._smooth import smooth_scan


def test_fpfh_goes_first_only_when_both_clouds_are_smooth():
    assert choose_features([0.0, 0.05]).first == "fpfh"
    assert choose_features([SMOOTH_SHARE, SMOOTH_SHARE]).first == "fpfh"  # at most: smooth
    assert choose_features([0.05, 0.2]).first == "byoc"  # one cloud with edges: learned first
    assert choose_features([0.8, 0.7]).first == "byoc"
    picked = choose_features([0.01, 0.02]).as_dict()
    assert picked["first"] == "fpfh" and picked["rough_share"] == [0.01, 0.02]
    assert picked["smooth_share"] == SMOOTH_SHARE and "FPFH features" in picked["reason"]


def test_an_object_below_the_trained_size_starts_with_fpfh_rough_or_not():
    rough = choose_features([0.8, 0.7], small=True)
    assert rough.first == "fpfh" and rough.small_object
    assert rough.reason.startswith("an object below the trained size (80 %, 70 %")
    assert rough.as_dict()["small_object"] is True
    smooth = choose_features([0.01, 0.02], small=True)  # smooth says why first
    assert smooth.first == "fpfh" and smooth.reason.startswith("smooth surfaces")
    assert choose_features([0.8, 0.7]).as_dict()["small_object"] is False
    unmeasured = choose_features((), small=True)  # a small pair needs no shares
    assert unmeasured.first == "fpfh" and unmeasured.small_object
    assert unmeasured.reason.startswith("an object below the trained size: FPFH features")
    assert unmeasured.as_dict()["rough_share"] == []


@pytest.mark.parametrize(("radius", "first"), [(0.05, "fpfh"), (0.149, "fpfh"), (0.15, "byoc")])
def test_the_choice_reads_the_size_from_the_clouds_scales(radius, first):
    measured = []

    def rough_share(points, voxel):
        measured.append(voxel)
        return 0.6

    made = SimpleNamespace(rough_share=rough_share)
    scales = [SimpleNamespace(radius=radius, even_radius=None)] * 2
    got = features_for(made, (np.zeros((5, 3)),) * 2, 0.01, scales)
    assert got.first == first  # the trained size: 0.15 m
    small = first == "fpfh"
    assert got.small_object is small
    # the shares of a small pair are not measured: it starts with FPFH whatever they are
    assert got.rough_share == (() if small else (0.6, 0.6))
    assert measured == ([] if small else [0.01, 0.01])


def test_only_learned_features_with_an_auto_voxel_and_the_fpfh_fallback_choose():
    def made(**kw):
        return SimpleNamespace(**{"features": "byoc", "auto_voxel": True, "fallback": "fpfh", **kw})

    assert applies(made())
    assert not applies(made(features="fpfh"))
    assert not applies(made(auto_voxel=False))  # a voxel given
    assert not applies(made(fallback=None))  # --fallback none


def _registration(
    confidence: float, features: str, T: np.ndarray | float = 1.0, rmse: float = 0.2
) -> Registration:
    if not isinstance(T, np.ndarray):
        T, tx = np.eye(4), T
        T[0, 3] = tx
    return Registration(
        T, confidence, confidence >= 0.45, 10, 20, 0.5, 0.5, 100, 100, 0.1, 0.05, features,
        "ransac", "multiscale", 1000, 100, 0, None, {"fit": 0.1}, cues={"rmse": rmse},
    )  # fmt: skip


class _Made:
    """A learned registrar's stand-in: FPFH gives ``fpfh`` (a confidence, or raises) at
    x = 2 m, and its repeats give ``repeats`` in turn (a ``T`` in metres, or None: it
    raises); ``calls`` records each call's seed and changes beyond :data:`SMOOTH_FPFH`."""

    fallback_below = 0.45
    recipe = SimpleNamespace(seed=0)

    def __init__(self, fpfh, repeats=None, rmse=0.2):
        self.fpfh, self.rmse = fpfh, rmse
        self.repeats = list(repeats or [])
        self.calls = []

    def fpfh_registration(self, clouds, scales, seed=None, changes=(), coarser=1.0):
        assert changes[: len(SMOOTH_FPFH)] == SMOOTH_FPFH and coarser == 1.0
        self.calls.append((seed, changes[len(SMOOTH_FPFH) :]))
        if len(self.calls) == 1:
            if self.fpfh is None:
                raise RegistrationError("no correspondences")
            return _registration(self.fpfh, "fpfh", 2.0, self.rmse)
        T = self.repeats.pop(0) if self.repeats else _shifted(0.0)
        if T is None:
            raise RegistrationError("no correspondences")
        return _registration(0.3, "fpfh", T)


def _shifted(dx: float, degrees: float = 0.0) -> np.ndarray:
    """The stand-in's FPFH pose (x = 2 m) moved by ``dx`` and turned by ``degrees`` about z
    through the origin (the source's centroid of :data:`_CLOUDS`)."""
    T = np.eye(4)
    T[:3, :3] = axis_angle_matrix(np.array([0.0, 0.0, np.radians(degrees)]))
    T[0, 3] = 2.0 + dx
    return T


_CLOUDS = (np.zeros((4, 3)), None)  # the source's centroid at the origin


def _learned(confidence, calls):
    def run():
        calls.append(1)
        return _registration(confidence, "byoc")

    return run


def test_fpfh_above_the_gate_is_kept_and_the_learned_features_never_run():
    calls = []
    picked = choose_features([0.0, 0.0])
    made = _Made(0.9)
    got = smooth_first(made, (None, None), [], _learned(0.99, calls), picked, scale=4.0)
    assert calls == [] and got.features == "fpfh" and got.passed
    assert len(made.calls) == 1 and got.reproduced is None  # above the gate: no repeats
    assert got.T_tgt_src[0, 3] == pytest.approx(0.5)  # metres into the target's units
    assert got.features_choice["first"] == "fpfh" and got.fallback is None
    assert "first" in got.timings


@pytest.mark.parametrize(
    ("fpfh", "learned", "kept"),
    [(0.15, 0.6, "byoc"), (0.15, 0.1, "fpfh"), (None, 0.2, "byoc")],
)
def test_below_the_gate_the_learned_features_run_and_the_more_confident_is_kept(
    fpfh, learned, kept
):
    calls = []
    picked = choose_features([0.0, 0.0])
    made = _Made(fpfh, rmse=REPRODUCE_RMSE * 1.1)  # no repeats
    got = smooth_first(made, (None, None), [], _learned(learned, calls), picked, None)
    assert calls == [1] and got.features == kept
    assert got.fallback["features"] == "byoc" and got.fallback["used"] == (kept == "byoc")
    assert got.fallback["first_confidence"] == fpfh and got.fallback["confidence"] == learned
    assert got.passed == (got.confidence >= 0.45)


@pytest.mark.parametrize("fpfh", [0.9, 0.15])
def test_without_a_second_opinion_fpfh_is_the_result_above_or_below_the_gate(fpfh):
    made = _Made(fpfh, rmse=REPRODUCE_RMSE * 1.1)  # no repeats
    got = smooth_first(made, (None, None), [], None, choose_features([0.0, 0.0]), None)
    assert got.features == "fpfh" and got.passed == (fpfh >= 0.45) and got.fallback is None
    with pytest.raises(RegistrationError, match="no correspondences"):
        smooth_first(_Made(None), (None, None), [], None, choose_features([0.0, 0.0]), None)


@pytest.mark.parametrize("fpfh", [0.0, 0.1, 0.3])
def test_a_result_below_the_gate_that_both_repeats_reproduce_passes(fpfh):
    made = _Made(fpfh)
    got = smooth_first(made, _CLOUDS, [], None, choose_features([0.0, 0.0]), scale=4.0, seed=5)
    assert got.confidence == REPRODUCED_CONFIDENCE and got.passed
    assert got.T_tgt_src[0, 3] == pytest.approx(0.5)  # in the target's units, as before
    assert made.calls == [(5, ()), (6, ()), (5, (("fitting__estimator", "sc2"),))]
    note = got.reproduced
    assert note["agree"] and note["model_confidence"] == fpfh
    assert [r["name"] for r in note["repeats"]] == ["next seed", "sc2"]
    assert all(r["degrees"] == 0.0 and r["shift"] == 0.0 for r in note["repeats"])
    assert "reproduce" in got.timings and "first" in got.timings


@pytest.mark.parametrize(
    "repeat",
    [
        _shifted(AGREE_VOXELS * 0.05 * 1.5),  # 3 voxels away (the stand-in's voxel: 5 cm)
        _shifted(0.0, AGREE_DEG * 1.5),  # turned 3 deg
        None,  # the repeat cannot register the pair
    ],
)
def test_a_result_that_a_repeat_does_not_reproduce_keeps_its_confidence(repeat):
    for order in ([repeat, _shifted(0.0)], [_shifted(0.0), repeat]):  # either repeat
        made = _Made(0.3, order)
        got = smooth_first(made, _CLOUDS, [], None, choose_features([0.0, 0.0]), None)
        assert got.confidence == 0.3 and not got.passed and not got.reproduced["agree"]
        assert len(made.calls) == 3


def test_a_repeat_within_the_tolerance_agrees():
    inside = [_shifted(AGREE_VOXELS * 0.05 * 0.9, AGREE_DEG * 0.9), _shifted(0.0)]
    got = smooth_first(_Made(0.3, inside), _CLOUDS, [], None, choose_features([0.0, 0.0]), None)
    assert got.reproduced["agree"] and got.passed


@pytest.mark.parametrize("fpfh", [0.45, 0.9])
def test_no_repeats_at_or_above_the_gate(fpfh):
    made = _Made(fpfh)
    got = smooth_first(made, _CLOUDS, [], None, choose_features([0.0, 0.0]), None)
    assert len(made.calls) == 1 and got.reproduced is None and got.confidence == fpfh


def test_no_repeats_for_a_result_that_ends_with_a_large_residual():
    made = _Made(0.3, rmse=REPRODUCE_RMSE * 1.1)  # a symmetric shape turned: it reproduces
    got = smooth_first(made, _CLOUDS, [], None, choose_features([0.0, 0.0]), None)
    assert len(made.calls) == 1 and got.reproduced is None and not got.passed


def test_the_repeats_seeds_wrap_at_64_bits():
    made = _Made(0.3)
    smooth_first(made, _CLOUDS, [], None, choose_features([0.0, 0.0]), None, seed=2**64 - 1)
    assert [seed for seed, _ in made.calls] == [2**64 - 1, 0, 2**64 - 1]


def test_the_repeats_gap_reads_the_turn_and_the_move_of_a_point():  # local.correction
    T = _shifted(0.0, 30.0)
    assert correction(T, T, np.array([1.0, 2.0, 3.0])) == (0.0, 0.0)
    degrees, shift = correction(T, _shifted(0.0), np.zeros(3))  # turned about the point
    assert degrees == pytest.approx(30.0) and shift == pytest.approx(0.0, abs=1e-12)
    degrees, shift = correction(T, _shifted(0.0), np.array([1.0, 0.0, 0.0]))
    assert shift == pytest.approx(2 * np.sin(np.radians(15.0)))  # a chord of the unit circle


class _Coarser(_Made):
    """:class:`_Made` whose FPFH at coarser features gives ``coarse[factor]`` (``(confidence,
    rmse)`` at x = 3 m, or None: it raises), each call recorded in ``coarser_calls``."""

    def __init__(self, fpfh, coarse, rmse=REPRODUCE_RMSE * 1.1):
        super().__init__(fpfh, rmse=rmse)
        self.coarse, self.coarser_calls = coarse, []

    def fpfh_registration(self, clouds, scales, seed=None, changes=(), coarser=1.0):
        if coarser == 1.0:
            return super().fpfh_registration(clouds, scales, seed, changes)
        self.coarser_calls.append((seed, changes[len(SMOOTH_FPFH) :], coarser))
        if self.coarse.get(coarser) is None:
            raise RegistrationError("no correspondences")
        confidence, rmse = self.coarse[coarser]
        return _registration(confidence, "fpfh", _shifted(1.0), rmse)


_SMALL = choose_features((), small=True)
_KEPT = COARSER_RMSE * 0.9  # a residual the tries keep
_TURNED = COARSER_RMSE * 1.05  # a symmetric shape turned: passes, with too large a residual


def test_an_object_below_the_gate_is_registered_again_with_coarser_features():
    made = _Coarser(0.2, {COARSER[0]: (0.7, _KEPT)})
    got = smooth_first(made, _CLOUDS, [], None, _SMALL, scale=4.0, seed=5)
    assert made.coarser_calls == [(5, (), COARSER[0])]  # no repeats: it passes
    assert got.confidence == 0.7 and got.passed and got.T_tgt_src[0, 3] == pytest.approx(0.75)
    note = got.features_choice["coarser"]
    assert note["used"] == COARSER[0] and note["first_confidence"] == 0.2
    assert note["tries"] == [{"factor": COARSER[0], "voxel_size": 0.05, "confidence": 0.7,
                              "rmse": _KEPT}]  # fmt: skip
    assert "coarser" in got.timings and "first" in got.timings


def test_the_next_factor_is_tried_when_the_first_is_not_kept():
    made = _Coarser(0.2, {COARSER[0]: (0.7, _TURNED), COARSER[1]: (0.6, _KEPT)})
    got = smooth_first(made, _CLOUDS, [], None, _SMALL, scale=4.0, seed=5)
    assert [factor for _, _, factor in made.coarser_calls] == list(COARSER)
    assert got.confidence == 0.6 and got.passed
    note = got.features_choice["coarser"]
    assert note["used"] == COARSER[1] and [t["confidence"] for t in note["tries"]] == [0.7, 0.6]


@pytest.mark.parametrize(
    "coarse",
    [
        (0.7, _TURNED),
        (0.3, REPRODUCE_RMSE * 1.1),  # below the gate, too large a residual to repeat
        None,  # cannot register the pair
    ],
)
def test_a_coarser_result_is_kept_only_when_it_passes_with_a_small_residual(coarse):
    made = _Coarser(0.2, dict.fromkeys(COARSER, coarse))
    got = smooth_first(made, _CLOUDS, [], None, _SMALL, scale=4.0)
    assert len(made.coarser_calls) == len(COARSER)
    assert got.confidence == 0.2 and not got.passed
    assert got.T_tgt_src[0, 3] == pytest.approx(0.5)  # the first result, in the target's units
    note = got.features_choice["coarser"]
    assert note["used"] is None
    assert [t["confidence"] for t in note["tries"]] == [coarse[0] if coarse else None] * 2


def test_a_coarser_result_below_the_gate_that_its_repeats_reproduce_is_kept():
    made = _Coarser(0.2, {COARSER[0]: (0.3, _KEPT)})
    got = smooth_first(made, _CLOUDS, [], None, _SMALL, None, seed=5)
    sc2 = (("fitting__estimator", "sc2"),)
    factor = COARSER[0]
    assert made.coarser_calls == [(5, (), factor), (6, (), factor), (5, sc2, factor)]
    assert got.confidence == REPRODUCED_CONFIDENCE and got.passed and got.reproduced["agree"]
    assert got.features_choice["coarser"]["used"] == factor


def test_no_coarser_retry_above_the_gate_or_for_a_smooth_pair_of_the_trained_size():
    above = _Coarser(0.9, dict.fromkeys(COARSER, (0.95, 0.1)))
    assert smooth_first(above, _CLOUDS, [], None, _SMALL, None).confidence == 0.9
    smooth = _Coarser(0.2, dict.fromkeys(COARSER, (0.95, 0.1)))
    got = smooth_first(smooth, _CLOUDS, [], None, choose_features([0.0, 0.0]), None)
    assert above.coarser_calls == smooth.coarser_calls == [] and got.confidence == 0.2
    assert "coarser" not in got.features_choice


def test_when_neither_registers_the_learned_features_error_is_raised():
    def fails():
        raise RegistrationError("only 2 correspondences")

    with pytest.raises(RegistrationError, match="only 2"):
        smooth_first(_Made(None), (None, None), [], fails, choose_features([0.0, 0.0]), None)


@pytest.mark.slow
def test_the_engine_starts_a_smooth_pair_with_fpfh_unless_told_no_fallback():
    import byoc_cli

    # 2 m long: inside the trained size, so its smoothness (not its size) sends it to FPFH
    smooth, other = smooth_scan(0) * 10, smooth_scan(1) * 10
    made = byoc_cli.Registrar(device="cpu")
    got = made.register(smooth, other)
    assert got.features_choice["first"] == "fpfh" and got.features == "fpfh"
    assert not made.extractor.loaded  # FPFH alone: the shipped encoder is never built
    assert not got.features_choice["small_object"]
    assert max(got.features_choice["rough_share"]) <= SMOOTH_SHARE
    assert "restarts" not in got.timings and got.cues["restart_return"] == 1.0
    assert got.max_points == 3000 and got.recipe["refinement"]["restarts"] is False
    learned = byoc_cli.Registrar(device="cpu", fallback=None)
    without = learned.register(smooth, other)
    assert without.features_choice is None and without.features == "byoc"
    assert learned.extractor.loaded


@pytest.mark.slow
@pytest.mark.parametrize("unit", [1.0, 1000.0])
def test_a_noisy_small_object_starts_with_fpfh_and_is_registered(unit):
    """The same object scan in metres (below the trained size) and in millimetres (read as
    an object: seen from its scanner 7 radii away) takes the same path."""
    import byoc_cli

    rng = np.random.default_rng(0)
    seen = np.array([0.0, 0.0, 0.5])  # the scanner at the origin, 50 cm away
    noise = (0.0, 2e-4, (40000, 3))  # range noise about half the scanner's step
    noisy = [smooth_scan(k, even=True) + seen + rng.normal(*noise) for k in (0, 1)]
    T = np.eye(4)
    T[:3, :3] = axis_angle_matrix(np.array([0.0, 0.0, np.radians(25.0)]))
    T[:3, 3] = [0.02, -0.01, 0.03]
    target = noisy[1] @ T[:3, :3].T + T[:3, 3]
    got = byoc_cli.Registrar(device="cpu").register(noisy[0] * unit, target * unit)
    assert got.features_choice["first"] == "fpfh" and got.features_choice["small_object"]
    assert got.features_choice["in_millimetres"] == (unit > 1)
    assert got.features_choice["rough_share"] == []  # small: FPFH whatever the noise reads
    assert got.features == "fpfh" and got.fallback is None and got.passed
    found = got.T_tgt_src.copy()
    found[:3, 3] /= unit
    degrees, shift = correction(found, T, noisy[0].mean(axis=0))
    assert degrees < 2.0 and shift < 0.005


@pytest.mark.realdata
@pytest.mark.slow
def test_a_room_starts_with_the_learned_features(shared_data):
    import byoc_cli

    demo = shared_data / "pairs" / "3dmatch_demo"
    got = byoc_cli.Registrar(device="cpu").register(demo / "source.ply", demo / "target.ply")
    assert got.features_choice["first"] == "byoc" and got.features == "byoc"
    assert min(got.features_choice["rough_share"]) > 0.5  # 0.68 and 0.79
