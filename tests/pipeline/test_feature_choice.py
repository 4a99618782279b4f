"""Which features a pair starts with: the rule by hand, FPFH first and the learned features as
its second opinion with stand-ins, and the whole engine on a smooth and a cluttered pair."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from byoc_cli.errors import RegistrationError
from byoc_cli.pipeline.feature_choice import (
    SMOOTH_FPFH,
    SMOOTH_SHARE,
    applies,
    choose_features,
    smooth_first,
)
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


def test_only_learned_features_with_an_auto_voxel_and_the_fpfh_fallback_choose():
    def made(**kw):
        return SimpleNamespace(**{"features": "byoc", "auto_voxel": True, "fallback": "fpfh", **kw})

    assert applies(made())
    assert not applies(made(features="fpfh"))
    assert not applies(made(auto_voxel=False))  # a voxel given
    assert not applies(made(fallback=None))  # --fallback none


def _registration(confidence: float, features: str, tx: float = 1.0) -> Registration:
    T = np.eye(4)
    T[0, 3] = tx
    return Registration(
        T, confidence, confidence >= 0.45, 10, 20, 0.5, 0.5, 100, 100, 0.1, 0.05, features,
        "ransac", "multiscale", 1000, 100, 0, None, {"fit": 0.1},
    )  # fmt: skip


class _Made:
    """A learned registrar's stand-in: FPFH gives ``fpfh`` (a confidence, or raises)."""

    fallback_below = 0.45

    def __init__(self, fpfh):
        self.fpfh = fpfh

    def fpfh_registration(self, clouds, scales, seed=None, changes=()):
        assert changes == SMOOTH_FPFH
        if self.fpfh is None:
            raise RegistrationError("no correspondences")
        return _registration(self.fpfh, "fpfh", tx=2.0)


def _learned(confidence, calls):
    def run():
        calls.append(1)
        return _registration(confidence, "byoc")

    return run


def test_fpfh_above_the_gate_is_kept_and_the_learned_features_never_run():
    calls = []
    picked = choose_features([0.0, 0.0])
    got = smooth_first(_Made(0.9), (None, None), [], _learned(0.99, calls), picked, scale=4.0)
    assert calls == [] and got.features == "fpfh" and got.passed
    assert got.T_tgt_src[0, 3] == pytest.approx(0.5)  # metres into the target's units
    assert got.features_choice["first"] == "fpfh" and got.fallback is None
    assert "first" in got.timings


@pytest.mark.parametrize(
    ("fpfh", "learned", "kept"),
    [(0.3, 0.6, "byoc"), (0.3, 0.1, "fpfh"), (None, 0.2, "byoc")],
)
def test_below_the_gate_the_learned_features_run_and_the_more_confident_is_kept(
    fpfh, learned, kept
):
    calls = []
    picked = choose_features([0.0, 0.0])
    got = smooth_first(_Made(fpfh), (None, None), [], _learned(learned, calls), picked, None)
    assert calls == [1] and got.features == kept
    assert got.fallback["features"] == "byoc" and got.fallback["used"] == (kept == "byoc")
    assert got.fallback["first_confidence"] == fpfh and got.fallback["confidence"] == learned
    assert got.passed == (got.confidence >= 0.45)


@pytest.mark.parametrize("fpfh", [0.9, 0.3])
def test_without_a_second_opinion_fpfh_is_the_result_above_or_below_the_gate(fpfh):
    got = smooth_first(_Made(fpfh), (None, None), [], None, choose_features([0.0, 0.0]), None)
    assert got.features == "fpfh" and got.passed == (fpfh >= 0.45) and got.fallback is None
    with pytest.raises(RegistrationError, match="no correspondences"):
        smooth_first(_Made(None), (None, None), [], None, choose_features([0.0, 0.0]), None)


def test_when_neither_registers_the_learned_features_error_is_raised():
    def fails():
        raise RegistrationError("only 2 correspondences")

    with pytest.raises(RegistrationError, match="only 2"):
        smooth_first(_Made(None), (None, None), [], fails, choose_features([0.0, 0.0]), None)


@pytest.mark.slow
def test_the_engine_starts_a_smooth_pair_with_fpfh_unless_told_no_fallback():
    import byoc_cli

    smooth, other = smooth_scan(0), smooth_scan(1)
    got = byoc_cli.Registrar(device="cpu").register(smooth, other)
    assert got.features_choice["first"] == "fpfh" and got.features == "fpfh"
    assert max(got.features_choice["rough_share"]) <= SMOOTH_SHARE
    assert "restarts" not in got.timings and got.cues["restart_return"] == 1.0
    assert got.max_points == 3000 and got.recipe["refinement"]["restarts"] is False
    without = byoc_cli.Registrar(device="cpu", fallback=None).register(smooth, other)
    assert without.features_choice is None and without.features == "byoc"


@pytest.mark.realdata
@pytest.mark.slow
def test_a_room_starts_with_the_learned_features(shared_data):
    import byoc_cli

    demo = shared_data / "pairs" / "3dmatch_demo"
    got = byoc_cli.Registrar(device="cpu").register(demo / "source.ply", demo / "target.ply")
    assert got.features_choice["first"] == "byoc" and got.features == "byoc"
    assert min(got.features_choice["rough_share"]) > 0.5  # 0.68 and 0.79
