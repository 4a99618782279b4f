"""The confidence of a local registration (``--init``): the probability that its transform is
right, within 5 deg and 10 cm (at other scales: the same in refinement voxels of 2.5 cm).

A local registration has no correspondences to count; what it knows about its own result is
how the clouds meet there (the refinement's fitness and residual, the share of the source next
to the target, the conditioning of the point-to-plane normal equations), whether the coarse
pass already met the target where the refinement ended (its fitness, how far the refinement
moved its end), whether the refinements from the guess and from the coarse pass agree (and
how much better the one not kept fits) and how far the result lies from the guess.
:data:`COEFFICIENTS` are a logistic regression on these cues
(:func:`byoc_cli.pipeline.confidence.fit_logistic`), fitted by ``python benchmarks/init.py
fit`` (the module ``benchmarks/_init_calibration.py``) on local registrations of the posed
RGB-D sequences of ``../shared/data`` from guesses perturbed by 0-15 deg / 0-40 cm and, as
hard cases, 30-60 deg / 0.5-1 m; see the comment there.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

#: the transformed cues the model reads, in order
FEATURES = (
    "fitness",
    "rmse",
    "overlap",
    "coarse_fitness",
    "full_rank",
    "log_conditioning",
    "log_shift_deg",
    "log_shift_voxels",
    "log_correction_deg",
    "log_correction_voxels",
    "agree",
    "other_gain",
)
#: fitted weights of :data:`FEATURES`, then the bias: ``python benchmarks/init.py collect
#: --out calib.jsonl`` then ``fit calib.jsonl`` (seed 0): 310 local registrations of 62 posed
#: pairs (tum_fr1_desk_full at 10, 25 and 40 frames, tum_fr1_rpy at 20 and 50, tum_fr3_cabinet
#: at 1 and 3 keyframes, realsense_tabletop at 5 and 15, tum_fr1_desk and tum_fr1_xyz at 4;
#: 8 pairs a set at most), 186 from guesses 0-15 deg / 0-40 cm off (137 right) and 124 from
#: guesses 30-60 deg / 0.5-1 m off (44 right, 27 inside the trust region); right = within 5 deg
#: and 10 cm of the ground truth refined on the data (the ground truth where Open3D's refinement
#: disagrees). Sequence-grouped cross-validation at the default ``--min-confidence`` 0.45: 146
#: passed, 132 of them right (precision 90.4 %; 97.2 % without tum_fr3_cabinet, whose
#: symmetric poses 15 deg apart fit alike), 96.4 % of the right results inside the trust
#: region passed, and no registration from a far guess passed.
COEFFICIENTS = (
    1.1654,
    -0.7437,
    -0.2855,
    -0.0377,
    0.5327,
    2.8530,
    0.0699,
    -0.8452,
    -1.4064,
    0.3157,
    0.4942,
    0.5955,
    8.3173,
)
#: the other refinement's fitness gain counts up to this either way
OTHER_GAIN_CLIP = 0.1


def local_cue_vector(cues: Mapping[str, float]) -> list[float]:
    """The model inputs (:data:`FEATURES`) of one local registration's cues."""
    rmse = cues["rmse"]
    return [
        cues["fitness"],
        min(rmse, 5.0) if math.isfinite(rmse) else 5.0,
        cues["overlap"],
        cues["coarse_fitness"],
        1.0 if cues["rank"] >= 6 else 0.0,
        math.log10(max(cues["conditioning"], 1e-9)),
        math.log(cues["shift_deg"] + 0.1),
        math.log(cues["shift_voxels"] + 0.01),
        math.log(cues["correction_deg"] + 0.1),
        math.log(cues["correction_voxels"] + 0.01),
        cues["agree"],
        min(max(cues["other_gain"], -OTHER_GAIN_CLIP), OTHER_GAIN_CLIP) / OTHER_GAIN_CLIP,
    ]


def local_probability(cues: Mapping[str, float], coefficients=COEFFICIENTS) -> float:
    """The calibrated probability in [0, 1] that a local registration is right (0.0 when
    the refinement met the target nowhere: fitness 0)."""
    if cues["fitness"] <= 0.0:
        return 0.0
    z = sum(w * x for w, x in zip(coefficients[:-1], local_cue_vector(cues), strict=True))
    z += coefficients[-1]
    return 0.5 * (1.0 + math.tanh(0.5 * z))
