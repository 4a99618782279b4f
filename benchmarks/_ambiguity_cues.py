"""Ambiguity cues of one registered pair (benchmarks/ambiguity.py): how distinct the reported
pose is from the best *different* pose its correspondences or its clouds support.

Every cue reads what a run of ``byoc register`` has at hand after its verdict: the
correspondences ``p, q (K, 3)``, ``w (K,)``, the inlier threshold, the reported (refined)
``T1 (4, 4)``, the kept points and the prepared full clouds of the refinement. Everything is
batched torch, every draw from a seeded ``torch.Generator``.

* ``seq_*`` (sequential RANSAC): RANSAC on the correspondences outside ``T1``'s inliers; a
  pose within ``ELSEWHERE_DEG`` and ``FAR_VOXELS`` of ``T1`` has its inliers set aside too and
  RANSAC runs again, up to ``ROUNDS`` times. ``seq_ratio``: the inliers of the first pose
  more than ``ELSEWHERE_DEG`` or ``ELSEWHERE_VOXELS`` from ``T1`` over ``T1``'s (0 when
  none), ``seq_wratio`` the same in ratio weights, ``seq_voxels`` its distance; ``seq_far_*``
  the same for the first pose beyond ``FAR_VOXELS``.
* ``ref_*`` (those poses refined): ``T1`` and the poses found elsewhere refined together by
  the multiscale refinement on ``RESTART_POINTS`` source points per level (one batched run, as
  the restarts); ``ref_ratio``: the fitness of the best end still elsewhere over ``T1``'s end
  (0 when every end came back to ``T1``'s place); ``ref_overlap_ratio``: the same with the
  verdict's overlap (kept source points next to a kept target point).
* ``slide_*`` (top-k hypotheses): ``DRAWS`` seeded minimal sets scored at once; among the
  ``TOP_K`` with most inliers, those turned less than ``ELSEWHERE_DEG`` from ``T1`` and with
  at least half the top count: ``slide_voxels`` is the farthest one's displacement of the
  source centroid from ``T1``'s, in feature voxels (a slide: same rotation, translation
  elsewhere), ``slide_ratio`` its inlier count over ``T1``'s.
"""

from __future__ import annotations

import math
import time

import torch

from byoc_cli.fitting import ransac
from byoc_cli.fitting.procrustes import weighted_procrustes
from byoc_cli.fitting.ransac import _CandidateScorer, _edge_lengths, _sample_triplets
from byoc_cli.geometry import apply_transform
from byoc_cli.geometry.voxel import near_occupied
from byoc_cli.pipeline.restarts import RESTART_POINTS, refine_starts

#: a pose is elsewhere than another when it is turned more than this (degrees) ...
ELSEWHERE_DEG = 5.0
#: ... or moves the source centroid more than this many feature voxels
ELSEWHERE_VOXELS = 3.0
#: ... and far (a slide along repeated structure moves it 50 to 80 voxels)
FAR_VOXELS = 10.0
#: sequential RANSAC rounds at most (a round that lands near the first sets it aside)
ROUNDS = 4
#: RANSAC draws of a sequential round at most (the remainder is mostly outliers: no early stop)
SEQ_ITERATIONS = 20_000
#: minimal sets of the top-k hypotheses
DRAWS = 8192
TOP_K = 32


def pose_distance(T_a: torch.Tensor, T_b: torch.Tensor, centroid: torch.Tensor):
    """``(degrees, metres)``: the rotation between ``T_a`` and ``T_b (.., 4, 4)`` and how far
    apart they put the source point ``centroid (3,)``."""
    R = T_a[..., :3, :3].transpose(-1, -2) @ T_b[..., :3, :3]
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
    moved_a = T_a[..., :3, :3] @ centroid + T_a[..., :3, 3]
    moved_b = T_b[..., :3, :3] @ centroid + T_b[..., :3, 3]
    return torch.rad2deg(torch.arccos(cos)), torch.linalg.vector_norm(moved_b - moved_a, dim=-1)


def _elsewhere(deg, metres, voxel: float, voxels: float):
    return (deg > ELSEWHERE_DEG) | (metres > voxels * voxel)


def _residual(T: torch.Tensor, p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    return torch.linalg.vector_norm(apply_transform(T, p) - q, dim=1)


def sequential(p, q, w, T1, threshold, centroid, voxel, generator):
    """The ``seq_*`` cues and the poses found elsewhere (up to two: the first beyond
    ``ELSEWHERE_VOXELS``, the first beyond ``FAR_VOXELS``)."""
    inlier1 = _residual(T1, p, q) < threshold
    n1 = max(int(inlier1.sum()), 1)
    w1 = float(w[inlier1].sum()) or 1.0
    rest = ~inlier1
    out = {f"seq{tag}_{k}": 0.0 for tag in ("", "_far") for k in ("ratio", "wratio", "voxels")}
    poses = []
    for _ in range(ROUNDS):
        if int(rest.sum()) < 3:
            break
        keep = rest.nonzero().squeeze(1)
        fit = ransac(p[keep], q[keep], threshold, SEQ_ITERATIONS, generator=generator)
        if fit.num_inliers < 3:
            break
        T2 = fit.T_tgt_src.to(torch.float64)
        deg, metres = pose_distance(T1, T2, centroid)
        found = {
            "ratio": fit.num_inliers / n1,
            "wratio": float(w[keep[fit.inlier_mask]].sum()) / w1,
            "voxels": float(metres) / voxel,
        }
        if not poses and bool(_elsewhere(deg, metres, voxel, ELSEWHERE_VOXELS)):
            out.update({f"seq_{k}": v for k, v in found.items()})
            poses.append(T2)
        if bool(_elsewhere(deg, metres, voxel, FAR_VOXELS)):
            out.update({f"seq_far_{k}": v for k, v in found.items()})
            if poses[-1] is not T2:
                poses.append(T2)
            break
        rest[keep[fit.inlier_mask]] = False  # near the first: set it aside, look again
    return out, poses


def refined_second(clouds, T1, poses, kept, centroid, feature_voxel, refine_voxel):
    """The ``ref_*`` cues: ``T1`` and the ``poses`` found elsewhere refined together
    (``clouds``: the prepared :class:`~byoc_cli.pipeline.refine_levels.RefineCloud` pair;
    ``kept``: the kept points); the best end still elsewhere after it counts."""
    out = {"ref_ratio": 0.0, "ref_overlap_ratio": 0.0, "ref_voxels": 0.0, "ref_gain": -1.0}
    if not poses:
        return out
    starts = torch.stack([T1, *poses]).to(torch.float64)
    ends, fitness = refine_starts(*clouds, starts, refine_voxel, max_source_points=RESTART_POINTS)
    deg, metres = pose_distance(ends[:1], ends[1:], centroid)
    away = _elsewhere(deg, metres, feature_voxel, ELSEWHERE_VOXELS)
    if not bool(away.any()):
        return out  # every pose slid back into the first's place
    best = int(torch.argmax(torch.where(away, fitness[1:], -1.0)))
    src, tgt = kept
    overlap = [
        float(near_occupied(apply_transform(T, src), tgt, feature_voxel).float().mean())
        for T in (ends[0], ends[1 + best])
    ]
    return {
        "ref_ratio": float(fitness[1 + best] / fitness[0].clamp_min(1e-12)),
        "ref_overlap_ratio": overlap[1] / max(overlap[0], 1e-12),
        "ref_voxels": float(metres[best]) / feature_voxel,
        "ref_gain": float(fitness[1 + best] - fitness[0]),
    }


def top_k_slide(p, q, T1, threshold, centroid, voxel, generator):
    """The ``slide_*`` cues from ``DRAWS`` minimal sets scored at once."""
    out = {"slide_voxels": 0.0, "slide_ratio": 0.0}
    if len(p) < 3:
        return out
    idx = _sample_triplets(len(p), DRAWS, generator)
    sp, sq = p[idx], q[idx]
    ds, dt = _edge_lengths(sp), _edge_lengths(sq)
    ok = ((ds >= 0.9 * dt) & (dt >= 0.9 * ds)).all(-1)
    if int(ok.sum()) == 0:
        return out
    T = weighted_procrustes(sp[ok], sq[ok], None, warn_degenerate=False)
    count, _ = _CandidateScorer(p, q, threshold)(T)
    top = torch.topk(count, min(TOP_K, len(count))).indices
    T, count = T[top], count[top]
    deg, metres = pose_distance(T1.expand_as(T), T, centroid)
    n1 = max(int((_residual(T1, p, q) < threshold).sum()), 1)
    keep = (deg < ELSEWHERE_DEG) & (count >= 0.5 * count[0]) & (count >= 3)
    if not bool(keep.any()):
        return out
    far = int(torch.argmax(torch.where(keep, metres, -1.0)))
    return {"slide_voxels": float(metres[far]) / voxel, "slide_ratio": int(count[far]) / n1}


def ambiguity_cues(correspondences, T1, threshold, kept, clouds, voxels, seed: int) -> dict:
    """Every cue of one result, and ``cue_seconds``: what they took.

    Args:
        correspondences: ``(p, q, w)`` the estimator saw.
        T1: ``(4, 4)`` the reported result.
        threshold: the inlier threshold (metres).
        kept: the kept points of source and target (the verdict's overlap is theirs).
        clouds: the refinement's prepared clouds.
        voxels: ``(feature voxel, refinement voxel)``.
        seed: seeds the cues' generator.
    """
    start = time.perf_counter()
    p, q, w = correspondences
    T1 = T1.to(torch.float64)
    voxel, refine_voxel = voxels
    centroid = kept[0].to(torch.float64).mean(0)
    generator = torch.Generator().manual_seed(seed)
    seq, poses = sequential(p, q, w, T1, threshold, centroid, voxel, generator)
    ref = refined_second(clouds, T1, poses, kept, centroid, voxel, refine_voxel)
    slide = top_k_slide(p, q, T1, threshold, centroid, voxel, generator)
    cues = {**seq, **ref, **slide}
    assert all(math.isfinite(v) for v in cues.values()), cues
    return {**cues, "cue_seconds": time.perf_counter() - start}
