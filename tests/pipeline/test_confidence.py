"""The confidence model: the logistic fit recovers a known model, the probability is in
[0, 1], more inliers never lower it, and degenerate cues stay finite."""

from __future__ import annotations

import math

import numpy as np
import pytest

from byoc_cli.pipeline.confidence import (
    COEFFICIENTS,
    DEFAULT_MIN_CONFIDENCE,
    FEATURES,
    MODELS,
    cue_matrix,
    cue_vector,
    fit_logistic,
    probability_right,
    sigmoid,
)

CUES = {
    "inlier_share": 0.12,
    "inlier_ratio": 0.1,
    "inliers": 500.0,
    "overlap": 0.6,
    "coarse_inlier_ratio": 0.11,
    "fitness": 0.6,
    "rmse": 0.27,
    "rank": 6.0,
    "conditioning": 0.05,
    "shift_deg": 1.5,
    "shift_voxels": 1.2,
}


def test_fit_recovers_a_known_logistic_model():
    rng = np.random.default_rng(0)
    X = rng.standard_normal((20000, 3))
    w_true = np.array([1.5, -2.0, 0.5, 0.3])
    y = (rng.uniform(size=len(X)) < sigmoid(X @ w_true[:-1] + w_true[-1])).astype(float)
    w = fit_logistic(X, y, l2=1e-6)
    assert np.abs(w - w_true).max() < 0.1


def test_sigmoid_does_not_overflow():
    assert sigmoid(1e6) == 1.0 and sigmoid(-1e6) == 0.0 and sigmoid(0.0) == 0.5


def test_the_shipped_models_have_a_weight_per_feature_and_a_default_in_range():
    assert set(MODELS) == {"byoc", "fpfh", "byoc-unrefined", "fpfh-unrefined"}
    assert MODELS["byoc"] == COEFFICIENTS
    for coefficients in MODELS.values():
        assert len(coefficients) == len(FEATURES) + 1
        assert any(c != 0 for c in coefficients)  # fitted, not the scaffold's zeros
    assert 0.0 < DEFAULT_MIN_CONFIDENCE < 1.0


def test_the_register_config_names_a_known_confidence_model():
    from byoc_cli.pipeline.register import RegisterConfig

    assert RegisterConfig().confidence_model == "byoc"
    assert RegisterConfig(confidence_model="fpfh").confidence_model == "fpfh"
    with pytest.raises(ValueError, match="confidence_model"):
        RegisterConfig(confidence_model="sift")


def test_probability_is_in_range_and_finite_for_degenerate_cues():
    assert 0.0 <= probability_right(CUES) <= 1.0
    worst = {**CUES, "inlier_share": 0.0, "inlier_ratio": 0.0, "inliers": 0.0}
    worst.update(rmse=float("nan"), conditioning=0.0, shift_deg=0.0, shift_voxels=0.0)
    assert math.isfinite(cue_vector(worst).sum())
    assert 0.0 <= probability_right(worst) <= 1.0


def test_a_result_with_many_more_inliers_is_trusted_more():
    few = {**CUES, "inlier_share": 0.01, "inlier_ratio": 0.01, "inliers": 30.0}
    many = {**CUES, "inlier_share": 0.3, "inlier_ratio": 0.3, "inliers": 1500.0}
    assert probability_right(many) > probability_right(few)


def test_cue_matrix_shapes():
    assert cue_matrix([]).shape == (0, len(FEATURES))
    assert cue_matrix([CUES, CUES]).shape == (2, len(FEATURES))


def test_a_wrong_number_of_coefficients_is_refused():
    with pytest.raises(ValueError):
        probability_right(CUES, coefficients=(1.0, 2.0))
