"""Validation during training: register posed pairs with the geometric encoder only.

The test-time pipeline (the paper's section 4.1): the kept points of each view (voxelised,
first point per voxel), their geometric features, ratio-test top-200 correspondences per
direction and randomized Procrustes (100 subsets of 20). Source = view 1, target = view 0; the
estimate is compared with ``T_gt = inv(T_world_cam_i) @ T_world_cam_j``.

Besides the pose errors, validation measures the features themselves: the share of the
400 correspondences that are inliers under ``T_gt`` (``|T_gt p - q| < 10 cm``, the tau1 of the
paper's section 4.2) and the share of pairs above tau2 = 5 % (BYOC's "corr" feature-match
recall). On pairs that barely move, inliers under ``T_gt`` can be as close under the identity,
so the share is read together with the pose accuracy.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from byoc_cli.geometry import correspondence_inlier_ratio, rotation_error_deg, translation_error
from byoc_cli.training.data import PairDataset

ROT_THRESHOLDS_DEG = (5.0, 10.0, 45.0)
TRANS_THRESHOLDS_CM = (5.0, 10.0, 25.0)
#: metres: a correspondence is an inlier under the ground truth below this (tau1)
INLIER_DISTANCE = 0.10
#: a pair counts as recalled when its inlier share is above this (tau2)
INLIER_RATIO = 0.05


class PairErrors(NamedTuple):
    """Per-pair errors.

    Attributes:
        rotation_deg: ``(P,)`` float64.
        translation_cm: ``(P,)`` float64.
        inlier_ratio: ``(P,)`` float64 share of the correspondences within
            :data:`INLIER_DISTANCE` under the ground truth, or None when not measured.
    """

    rotation_deg: torch.Tensor
    translation_cm: torch.Tensor
    inlier_ratio: torch.Tensor | None = None


class PairRegistration(NamedTuple):
    """A test-time registration and the correspondences it was fitted to.

    Attributes:
        T_tgt_src: ``(4, 4)`` float64 estimate (CPU).
        points_src, points_tgt: ``(K, 3)`` float64 matched points (CPU).
    """

    T_tgt_src: torch.Tensor
    points_src: torch.Tensor
    points_tgt: torch.Tensor


def inlier_ratio(
    T_gt: torch.Tensor,
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    threshold: float = INLIER_DISTANCE,
) -> float:
    """Share of correspondences with ``|T_gt p - q| < threshold`` (0 when there is none).

    Args:
        T_gt: ``(4, 4)`` ground-truth ``T_tgt_src``.
        points_src, points_tgt: ``(K, 3)`` matched points.
    """
    return correspondence_inlier_ratio(points_src, points_tgt, T_gt, threshold)


def pose_accuracy(errors: PairErrors) -> dict[str, float]:
    """Accuracy (%) at 5/10/45 deg and 5/10/25 cm, mean and median errors.

    Returns:
        ``rot_acc_5``, ``rot_acc_10``, ``rot_acc_45``, ``rot_mean_deg``, ``rot_median_deg``,
        ``trans_acc_5``, ``trans_acc_10``, ``trans_acc_25``, ``trans_mean_cm``,
        ``trans_median_cm``, ``num_pairs`` (NaN statistics when there is no pair); with
        inlier ratios also ``inlier_pct_mean`` (mean share of inlier correspondences, %)
        and ``corr_fmr`` (% of pairs whose share is above :data:`INLIER_RATIO`).
    """
    rot = errors.rotation_deg.to(torch.float64)
    trans = errors.translation_cm.to(torch.float64)
    n = int(rot.numel())
    out: dict[str, float] = {}
    nan = float("nan")
    for thr in ROT_THRESHOLDS_DEG:
        out[f"rot_acc_{thr:g}"] = 100.0 * float((rot < thr).double().mean()) if n else nan
    out["rot_mean_deg"] = float(rot.mean()) if n else nan
    out["rot_median_deg"] = float(rot.median()) if n else nan
    for thr in TRANS_THRESHOLDS_CM:
        out[f"trans_acc_{thr:g}"] = 100.0 * float((trans < thr).double().mean()) if n else nan
    out["trans_mean_cm"] = float(trans.mean()) if n else nan
    out["trans_median_cm"] = float(trans.median()) if n else nan
    if errors.inlier_ratio is not None:
        ratio = errors.inlier_ratio.to(torch.float64)
        out["inlier_pct_mean"] = 100.0 * float(ratio.mean()) if n else nan
        out["corr_fmr"] = 100.0 * float((ratio > INLIER_RATIO).double().mean()) if n else nan
    out["num_pairs"] = float(n)
    return out


@torch.no_grad()
def register_pair_geometric(
    encoder: torch.nn.Module,
    coords_src: torch.Tensor,
    coords_tgt: torch.Tensor,
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    k: int = 200,
    generator: torch.Generator | None = None,
    **procrustes: int,
) -> PairRegistration:
    """``T_tgt_src`` from geometric features (test-time pipeline).

    Args:
        encoder: geometric encoder (``forward(coords (N, 4), feats (N, 3))``); used as is
            (call it in eval mode).
        coords_src, coords_tgt: ``(M, 3)`` int64 voxel coordinates of the kept points.
        points_src, points_tgt: ``(M, 3)`` the kept points.
        k: ratio-test matches per direction.
        generator: for the subsets.
        procrustes: ``num_subsets``, ``subset_size`` of :func:`randomized_procrustes`
            (default: its own).

    Returns:
        :class:`PairRegistration` (CPU).
    """
    from byoc_cli.fitting import randomized_procrustes
    from byoc_cli.matching import ratio_test_correspondences

    device = next(encoder.parameters()).device
    n_src = coords_src.shape[0]
    coords = torch.cat([coords_src, coords_tgt]).to(device)
    batch = torch.cat(
        [torch.zeros(n_src, dtype=torch.int64), torch.ones(coords_tgt.shape[0], dtype=torch.int64)]
    )
    coords4 = torch.cat([batch.to(device)[:, None], coords], dim=1)
    feats = encoder(coords4, torch.ones(coords4.shape[0], 3, device=device)).float().cpu()
    corr = ratio_test_correspondences(feats[:n_src], feats[n_src:], k=k)
    p = points_src[corr.src_idx].to(torch.float64)
    q = points_tgt[corr.tgt_idx].to(torch.float64)
    fit = randomized_procrustes(
        p,
        q,
        corr.weight.to(torch.float64),
        generator=generator,
        **procrustes,
    )
    return PairRegistration(fit.T_tgt_src.to(torch.float64).cpu(), p.cpu(), q.cpu())


def validate(
    encoder: torch.nn.Module,
    dataset: PairDataset,
    k: int = 200,
    seed: int = 0,
) -> tuple[dict[str, float], PairErrors]:
    """Register every pair of ``dataset`` and summarise the pose errors.

    The encoder is switched to eval mode for the duration and put back in its previous
    mode afterwards. The randomized Procrustes generator is seeded with ``seed`` per
    call, so validation never touches the training RNG streams.

    Args:
        encoder: geometric encoder.
        dataset: a :class:`PairDataset` built ``with_poses=True``.
        k: correspondences per direction.
        seed: randomized-Procrustes seed.

    Returns:
        ``(metrics, errors)`` (see :func:`pose_accuracy`); pairs without ground truth
        are skipped.
    """
    was_training = encoder.training
    encoder.eval()
    generator = torch.Generator().manual_seed(seed)
    rot, trans, inliers = [], [], []
    try:
        for index in range(len(dataset)):
            sample = dataset[index]
            if sample.T_gt is None:
                continue
            v0, v1 = sample.view0, sample.view1
            if min(v0.point_index.numel(), v1.point_index.numel()) < 3:
                continue
            reg = register_pair_geometric(
                encoder,
                v1.coords,
                v0.coords,
                v1.points[v1.point_index],
                v0.points[v0.point_index],
                k=k,
                generator=generator,
            )
            rot.append(float(rotation_error_deg(reg.T_tgt_src, sample.T_gt)))
            trans.append(100.0 * float(translation_error(reg.T_tgt_src, sample.T_gt)))
            inliers.append(inlier_ratio(sample.T_gt, reg.points_src, reg.points_tgt))
    finally:
        encoder.train(was_training)
    errors = PairErrors(
        torch.tensor(rot, dtype=torch.float64),
        torch.tensor(trans, dtype=torch.float64),
        torch.tensor(inliers, dtype=torch.float64),
    )
    return pose_accuracy(errors), errors
