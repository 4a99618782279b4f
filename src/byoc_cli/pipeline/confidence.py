"""The confidence of a registration: the probability that its transform is right.

Right means within 5 deg and 10 cm of the truth (at other scales: the same after the auto
voxel brought the data to the features' scale). The probability is a logistic regression on
what the run already knows about its own result (:attr:`RegistrationResult.cues`): the
ratio-weighted inlier share, the inlier ratio and count, the overlap, the inlier ratio of the
robust fit before refinement, the refinement's fitness, residual and rank, and how far the
refinement moved the robust fit, and whether restarts of the refinement from turned starts
come back to the result or find a better fit elsewhere. :data:`COEFFICIENTS` are fitted on
the development set of ``benchmarks/confidence.py`` (its failures included) and the default
``--min-confidence`` (:data:`DEFAULT_MIN_CONFIDENCE`) is the threshold chosen there, both
printed by
``python benchmarks/confidence.py fit DEV.jsonl``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy is imported where it is used: the recipe reads this module's gate
    import numpy as np

#: the transformed cues the model reads, in order
FEATURES = (
    "logit_inlier_share",
    "logit_inlier_ratio",
    "log_inliers",
    "overlap",
    "coarse_inlier_ratio",
    "fitness",
    "rmse",
    "full_rank",
    "log_conditioning",
    "log_shift_deg",
    "log_shift_voxels",
    "restart_return",
    "restart_gain",
)
#: fitted weights of :data:`FEATURES`, then the bias, for the learned features
#: (``python benchmarks/confidence.py fit`` on its development set of 320 pairs: 311
#: registered, 225 of them right against the ground truth refined on the data, 9 refused)
COEFFICIENTS = (
    -0.1800,
    0.3863,
    0.7854,
    -0.8484,
    0.6124,
    0.0260,
    -0.2598,
    -0.0897,
    1.6314,
    0.3773,
    -0.2034,
    2.1945,
    -1.0458,
    -1.4725,
)
#: the default ``--min-confidence`` of ``register`` and ``register-batch``: the highest
#: threshold that keeps 95 % of the right results of the development set in its grouped
#: cross-validation, with the FPFH fallback below it (precision there: 82.3 %, recall 95.2 %;
#: see docs/confidence.md)
DEFAULT_MIN_CONFIDENCE = 0.45
#: the same for FPFH features refined by the multiscale ICP (the learned features' fallback),
#: fitted on the 115 FPFH registrations of the pairs where the learned features' confidence
#: was low (34 right)
FPFH_COEFFICIENTS = (
    0.1092,
    0.6610,
    1.0936,
    0.0320,
    0.0125,
    0.5711,
    -0.0933,
    0.1571,
    1.2644,
    -0.1496,
    0.0921,
    0.7363,
    -0.5455,
    -1.0763,
)
#: the same for results that the multiscale ICP did not refine (``--refine none``, the default
#: of ``--features fpfh``; ``icp``), whose fit cues :func:`~byoc_cli.pipeline.refine.measure_fit`
#: measures at the returned transform: ``python benchmarks/confidence.py collect --refine none``
#: on the same 320 pairs (311 registered each; 164 learned and 140 FPFH results right), then
#: ``fit``. The shift and restart cues are constant there (weight 0). In its grouped
#: cross-validation, at :data:`DEFAULT_MIN_CONFIDENCE`: precision 70.9 %, recall 81.7 %
#: (learned), 68.2 % / 87.1 % (FPFH)
UNREFINED_COEFFICIENTS = (
    -0.2883,
    -0.3485,
    2.2746,
    -1.5063,
    0.1448,
    0.4037,
    -0.1602,
    0.1946,
    2.6591,
    0.0,
    0.0,
    0.0,
    0.0,
    -10.6990,
)
FPFH_UNREFINED_COEFFICIENTS = (
    -0.4269,
    0.2366,
    1.8489,
    -0.2141,
    -0.0362,
    1.0768,
    -0.4913,
    0.0315,
    2.1547,
    0.0,
    0.0,
    0.0,
    0.0,
    -6.5038,
)
#: the kinds of features a model is chosen by (``RegisterConfig.confidence_model``)
MODEL_KINDS = ("byoc", "fpfh")
#: the coefficients of each kind of features, refined by the multiscale ICP or not
#: (``"<kind>-unrefined"``)
MODELS = {
    "byoc": COEFFICIENTS,
    "fpfh": FPFH_COEFFICIENTS,
    "byoc-unrefined": UNREFINED_COEFFICIENTS,
    "fpfh-unrefined": FPFH_UNREFINED_COEFFICIENTS,
}

_EPS = 1e-4
#: the restart gain (a share of the source points) counts up to this either way
RESTART_GAIN_CLIP = 0.05


def _logit(x: float) -> float:
    x = min(max(x, _EPS), 1 - _EPS)
    return math.log(x / (1 - x))


def cue_vector(cues: Mapping[str, float]) -> np.ndarray:
    """``(len(FEATURES),)`` float64 model inputs of one run's cues."""
    import numpy as np

    rmse = cues["rmse"]
    return np.array(
        [
            _logit(cues["inlier_share"]),
            _logit(cues["inlier_ratio"]),
            math.log1p(cues["inliers"]),
            cues["overlap"],
            cues["coarse_inlier_ratio"],
            cues["fitness"],
            min(rmse, 5.0) if math.isfinite(rmse) else 5.0,
            1.0 if cues["rank"] >= 6 else 0.0,
            math.log10(max(cues["conditioning"], 1e-9)),
            math.log(cues["shift_deg"] + 0.1),
            math.log(cues["shift_voxels"] + 0.01),
            cues.get("restart_return", 1.0),
            min(max(cues.get("restart_gain", -1.0), -RESTART_GAIN_CLIP), RESTART_GAIN_CLIP)
            / RESTART_GAIN_CLIP,
        ]
    )


def cue_matrix(cues: Sequence[Mapping[str, float]]) -> np.ndarray:
    """``(R, len(FEATURES))`` float64: :func:`cue_vector` of each run."""
    import numpy as np

    return np.stack([cue_vector(c) for c in cues]) if cues else np.zeros((0, len(FEATURES)))


def sigmoid(z: np.ndarray | float) -> np.ndarray | float:
    """The logistic function, overflow-safe."""
    import numpy as np

    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(z, dtype=np.float64)))


def probability_right(
    cues: Mapping[str, float], coefficients: Sequence[float] = COEFFICIENTS
) -> float:
    """The calibrated probability in [0, 1] that the run's transform is right.

    Raises:
        ValueError: ``coefficients`` is not one weight per feature and a bias.
    """
    import numpy as np

    w = np.asarray(coefficients, dtype=np.float64)
    if w.shape != (len(FEATURES) + 1,):
        raise ValueError(f"expected {len(FEATURES) + 1} coefficients, got {w.shape}")
    return float(sigmoid(cue_vector(cues) @ w[:-1] + w[-1]))


def fit_logistic(
    X: np.ndarray, y: np.ndarray, l2: float = 1.0, iterations: int = 100
) -> np.ndarray:
    """L2-regularised logistic regression by Newton's method.

    Args:
        X: ``(R, F)`` inputs.
        y: ``(R,)`` labels in {0, 1}.
        l2: penalty on the weights (not the bias).
        iterations: Newton steps at most.

    Returns:
        ``(F + 1,)`` weights then bias.
    """
    import numpy as np

    R, F = X.shape
    A = np.column_stack([X, np.ones(R)])
    w = np.zeros(F + 1)
    penalty = np.full(F + 1, l2)
    penalty[-1] = 0.0
    for _ in range(iterations):
        p = sigmoid(A @ w)
        grad = A.T @ (p - y) + penalty * w
        H = (A * (p * (1 - p))[:, None]).T @ A + np.diag(penalty) + 1e-9 * np.eye(F + 1)
        step = np.linalg.solve(H, grad)
        w -= step
        if np.abs(step).max() < 1e-8:
            break
    return w
