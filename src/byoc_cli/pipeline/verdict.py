"""The verdict on one pair's registration: the cues a run knows about its own result and the
calibrated confidence they give (:func:`byoc_cli.pipeline.confidence.probability_right`).

A :class:`Judge` holds what stays fixed while a pair's result moves (its correspondences
``p, q (K, 3)``, ``w (K,)``, the robust fit ``T_coarse (4, 4)`` they gave, the kept points of
both clouds); called with a refinement of that fit, it returns its :class:`Verdict`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from byoc_cli.geometry import apply_transform
from byoc_cli.geometry.voxel import near_occupied
from byoc_cli.pipeline.confidence import MODELS, probability_right
from byoc_cli.pipeline.refine import Refinement

#: the restart cues of a result without restarts: no doubt (their most confident values)
NO_RESTARTS = {"restart_return": 1.0, "restart_gain": -1.0}


class Verdict(NamedTuple):
    """The cues of a result (:attr:`byoc_cli.pipeline.register.RegistrationResult.cues`),
    its confidence, its inliers among the judged correspondences and its overlap."""

    cues: dict[str, float]
    confidence: float
    num_inliers: int
    overlap: float


class Judge:
    """The cues and the confidence of a refinement of one pair's robust fit: the
    correspondences ``(p, q, w)`` (``(K, 3)``, ``(K, 3)``, ``(K,)``) it came from, the
    fit ``T_coarse (4, 4)`` and the kept points of ``src`` and ``tgt``."""

    def __init__(self, src, tgt, correspondences, T_coarse, voxel_size, threshold, config):
        self.src, self.tgt = src, tgt
        self.p, self.q, self.w = correspondences
        self.T_coarse, self.voxel_size, self.threshold = T_coarse, voxel_size, threshold
        # a result that the multiscale ICP did not refine has its own calibration
        kind = config.confidence_model
        self.model = MODELS[kind if config.refine == "multiscale" else f"{kind}-unrefined"]
        self.coarse = float(
            (
                torch.linalg.vector_norm(apply_transform(T_coarse, self.p) - self.q, dim=1)
                < threshold
            )
            .double()
            .mean()
        )

    def __call__(self, refinement: Refinement, restart_cues: dict[str, float]) -> Verdict:
        T, p, q, w = refinement.T_tgt_src, self.p, self.q, self.w
        residual = torch.linalg.vector_norm(apply_transform(T, p) - q, dim=1)
        inlier = residual < self.threshold
        num_inliers = int(inlier.sum())
        share = float(w[inlier].sum() / w.sum().clamp_min(1e-12)) if num_inliers >= 3 else 0.0
        moved = apply_transform(T, self.src.points)
        overlap = float(near_occupied(moved, self.tgt.points, self.voxel_size).float().mean())
        shift = T @ torch.linalg.inv(self.T_coarse)
        cues = {
            **restart_cues,
            "inlier_share": share,
            "inlier_ratio": num_inliers / p.shape[0],
            "inliers": float(num_inliers),
            "overlap": overlap,
            "coarse_inlier_ratio": self.coarse,
            "fitness": refinement.fitness,
            "rmse": refinement.rmse,
            "rank": float(refinement.rank),
            "conditioning": refinement.conditioning,
            "shift_deg": _angle_deg(shift[:3, :3]),
            "shift_voxels": float(torch.linalg.vector_norm(shift[:3, 3])) / self.voxel_size,
        }
        confidence = probability_right(cues, self.model) if num_inliers >= 3 else 0.0
        return Verdict(cues, confidence, num_inliers, overlap)


def _angle_deg(R: torch.Tensor) -> float:
    """Rotation angle of ``R (3, 3)`` in degrees."""
    cos = (float(torch.trace(R)) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))
