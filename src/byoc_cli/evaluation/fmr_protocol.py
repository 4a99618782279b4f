"""The feature-match recall protocol: its constants, the per-pair seed and subsets, and the
feature figures of one pair (nearest-neighbour and ratio-test inlier ratios)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import torch

from byoc_cli.evaluation.metrics import correspondence_inlier_ratio, nn_inlier_ratio
from byoc_cli.matching import ratio_test_correspondences
from byoc_cli.pipeline.features import CloudFeatures
from byoc_cli.pipeline.register import sample_subset


@dataclass(frozen=True)
class FmrConfig:
    """Settings of :func:`evaluate_fmr` (the protocol's constants by default).

    Attributes:
        tau1: inlier distance (m).
        tau2: inlier-ratio threshold of a recalled pair.
        num_samples: points sampled per fragment (0 = all kept points).
        top_k: ratio-test correspondences kept per direction for ``corr``.
        rmse_threshold: registration recall threshold on the official RMSE (m).
        success_rotation_deg, success_translation_m: the success-rate thresholds.
        seed: base seed of every random choice.
    """

    tau1: float = 0.10
    tau2: float = 0.05
    num_samples: int = 5000
    top_k: int = 200
    rmse_threshold: float = 0.2
    success_rotation_deg: float = 15.0
    success_translation_m: float = 0.30
    seed: int = 0


def pair_seed(seed: int, scene: str, i: int, j: int) -> int:
    """The seed of one pair: a hash of ``(seed, scene, i, j)`` in ``[0, 2**63)``."""
    digest = hashlib.sha256(f"{seed}/{scene}/{i}/{j}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def sample_pair_subsets(
    num_src: int, num_tgt: int, num_samples: int, seed: int
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The subsets of one pair: source first, then target, from one generator seeded ``seed``.

    Same draws as :func:`byoc_cli.pipeline.register.estimate_transform` with
    ``max_points=num_samples`` and the same seed. None means "all points".
    """
    generator = torch.Generator().manual_seed(seed)
    idx_src = sample_subset(num_src, num_samples, generator)
    idx_tgt = sample_subset(num_tgt, num_samples, generator)
    return idx_src, idx_tgt


def feature_metrics(
    src: CloudFeatures, tgt: CloudFeatures, T_gt: torch.Tensor, seed: int, config: FmrConfig
) -> dict[str, Any]:
    """FMR figures of one pair for one feature spec, on the pair's seeded subsets.

    Args:
        src, tgt: features of the source and target fragments.
        T_gt: ``(4, 4)`` float64, maps source into target.
        seed: :func:`pair_seed` of the pair.
        config: protocol settings (``tau1``, ``tau2``, ``num_samples``, ``top_k``).

    Returns:
        JSON-able dict: point and sample counts, nearest-neighbour ``inlier_ratio`` and
        ``recalled``, ratio-test ``corr_inlier_ratio`` and ``corr_recalled``.
    """
    idx_src, idx_tgt = sample_pair_subsets(
        len(src.points), len(tgt.points), config.num_samples, seed
    )
    ps, fs = (
        (src.points, src.feats) if idx_src is None else (src.points[idx_src], src.feats[idx_src])
    )
    pt, ft = (
        (tgt.points, tgt.feats) if idx_tgt is None else (tgt.points[idx_tgt], tgt.feats[idx_tgt])
    )
    nn = nn_inlier_ratio(ps, fs, pt, ft, T_gt, config.tau1)
    corr = ratio_test_correspondences(fs, ft, k=config.top_k)
    corr_ratio = correspondence_inlier_ratio(ps[corr.src_idx], pt[corr.tgt_idx], T_gt, config.tau1)
    return {
        "num_points_src": len(src.points),
        "num_points_tgt": len(tgt.points),
        "num_samples_src": int(ps.shape[0]),
        "num_samples_tgt": int(pt.shape[0]),
        "inlier_ratio": nn.inlier_ratio,
        "num_matches": nn.num_matches,
        "recalled": nn.inlier_ratio >= config.tau2,
        "corr_inlier_ratio": corr_ratio,
        "num_correspondences": int(corr.src_idx.numel()),
        "corr_recalled": corr_ratio >= config.tau2,
    }
