"""Pairwise registration: features -> ratio-test correspondences -> robust fit.

The settings (:class:`RegisterConfig`, from a recipe), the matching and the result are here;
the robust fit, its refinement and restarts are :mod:`byoc_cli.pipeline.solve`, the cues and
confidence of a result :mod:`byoc_cli.pipeline.verdict`.

The result's transform is ``T_tgt_src`` (4x4, float64, column vectors): it maps source
points into the target frame, ``x_tgt = R x_src + t``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import torch

from byoc_cli.errors import RegistrationError
from byoc_cli.geometry import apply_transform
from byoc_cli.matching import ratio_test_correspondences
from byoc_cli.pipeline.confidence import MODEL_KINDS
from byoc_cli.pipeline.features import CloudFeatures, FeatureExtractor
from byoc_cli.pipeline.recipe import ESTIMATORS, PAPER, RegistrationRecipe
from byoc_cli.pipeline.refine import Refinement
from byoc_cli.pipeline.solve import Solver
from byoc_cli.pipeline.verdict import Verdict
from byoc_cli.threads import Parallel

#: refinements after the robust fit
REFINERS = (None, "multiscale")
#: results less confident than this before the restarts skip them (they could only be less
#: confident after; on the development set no result below it passed the gate after them)
RESTART_FLOOR = 0.2


def restart_floor(min_confidence: float) -> float:
    """The restart floor under a gate of ``min_confidence``: :data:`RESTART_FLOOR`, or the
    gate when that is lower (a result that could pass it is never denied its restarts)."""
    return min(RESTART_FLOOR, min_confidence)


@dataclass(frozen=True)
class RegisterConfig:
    """Settings of :func:`estimate_transform` and :func:`register_clouds`, flat: a
    :class:`~byoc_cli.pipeline.recipe.RegistrationRecipe` gives them
    (:func:`register_config`); the defaults are the paper's
    (:data:`~byoc_cli.pipeline.recipe.PAPER`).

    Attributes:
        num_correspondences: top k ratio-test matches kept per direction (2k in all).
        max_points: size of the seeded random subset of kept points per cloud that enters
            matching (0 = all).
        estimator: ``"procrustes"`` (randomized Procrustes, the paper's), ``"ransac"`` or
            ``"sc2"`` (second-order spatial compatibility).
        num_subsets, subset_size: randomized Procrustes' candidates and their size.
        inlier_factor: inlier threshold as a multiple of the voxel size (RANSAC's threshold,
            and the threshold of the reported inliers and overlap).
        ransac_iterations, ransac_confidence: RANSAC's limits.
        refine: ``None`` or ``"multiscale"``
            (:func:`byoc_cli.pipeline.refine.refine_multiscale`: coarse to fine on the
            full-resolution clouds, degenerate directions held).
        restarts: after ``"multiscale"`` refinement, refine again from starts turned around the
            result (:func:`byoc_cli.pipeline.restarts.restart_refinement`), keep the end of best
            fitness when it is elsewhere and better by :data:`~byoc_cli.pipeline.solve.SWITCH_GAIN`,
            and report how the restarts agree (``restart_return``, ``restart_gain``).
        restart_floor: the restarts run only for a result whose confidence before them (with
            :data:`~byoc_cli.pipeline.verdict.NO_RESTARTS`, their most confident cues)
            reaches this: below it they could only lower it (:func:`restart_floor` of the
            gate's ``--min-confidence``).
        min_confidence: the gate (``--min-confidence``): an identity-like result of clouds
            sampled along lines gives way to a second try that reaches it
            (:func:`estimate_transform`).
        mutual: keep only mutual nearest neighbours before the top-k ratio-test selection
            (:func:`byoc_cli.matching.ratio_test_correspondences`).
        seed: seeds every random choice (subset, sampling).
        confidence_model: the features whose calibration turns the cues into the confidence
            (:data:`byoc_cli.pipeline.confidence.MODELS`).
        structure_check: a result that reaches ``min_confidence`` is checked against its
            turns about the up axis (:meth:`~byoc_cli.pipeline.solve.Solver.check_structure`);
            on with the recipe's ``matching.turns`` (``--turns``: scans declared turned about
            the vertical; the FPFH fallback on large panoramas).
        turn_rooms: the clouds are panoramas larger than the trained range
            (:func:`~byoc_cli.pipeline.fallback.large_panoramas`): where they are rooms
            (:attr:`~byoc_cli.pipeline.structure_check.RivalCheck.room_like`) every result is
            checked, each turn also starts where it overlays the most of the target, and a turn
            that fits what stands in the room better by
            :data:`~byoc_cli.pipeline.structure_check.ADOPT_GAIN` is taken instead (measured on
            rooms; on depth frames with ``--turns`` the occupancy starts find rivals among
            partial views, and objects centred on their origin are no rooms:
            docs/experiments/2026-11-28-room-turn-adoption.md).
    """

    num_correspondences: int = PAPER.matching.correspondences
    max_points: int = PAPER.matching.max_points
    estimator: str = PAPER.fitting.estimator
    num_subsets: int = PAPER.fitting.num_subsets
    subset_size: int = PAPER.fitting.subset_size
    inlier_factor: float = PAPER.fitting.inlier_factor
    ransac_iterations: int = PAPER.fitting.ransac_iterations
    ransac_confidence: float = PAPER.fitting.ransac_confidence
    refine: str | None = None
    mutual: bool = PAPER.matching.mutual
    restarts: bool = PAPER.refinement.restarts
    restart_floor: float = restart_floor(PAPER.gate.min_confidence)
    min_confidence: float = PAPER.gate.min_confidence
    seed: int = PAPER.seed
    chunk_size: int | None = None
    confidence_model: str = PAPER.features.kind
    structure_check: bool = PAPER.matching.turns is True
    turn_rooms: bool = False

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator must be one of {ESTIMATORS}, got {self.estimator!r}")
        if self.refine not in REFINERS:
            raise ValueError(f"refine must be one of {REFINERS}, got {self.refine!r}")
        if self.confidence_model not in MODEL_KINDS:
            raise ValueError(
                f"confidence_model must be one of {MODEL_KINDS}, got {self.confidence_model!r}"
            )
        if self.num_correspondences < 1 or self.max_points < 0:
            raise ValueError("num_correspondences must be >= 1 and max_points >= 0")


def register_config(recipe: RegistrationRecipe, refine: bool = True) -> RegisterConfig:
    """The :class:`RegisterConfig` of a recipe (``refine=False``: without its refinement,
    for callers that refine on their own: ``register-scans``, ``odometry``)."""
    method = recipe.refinement.method if refine else "none"
    fit = recipe.fitting
    return RegisterConfig(
        num_correspondences=recipe.matching.correspondences,
        max_points=recipe.matching.max_points,
        estimator=fit.estimator,
        num_subsets=fit.num_subsets,
        subset_size=fit.subset_size,
        inlier_factor=fit.inlier_factor,
        ransac_iterations=fit.ransac_iterations,
        ransac_confidence=fit.ransac_confidence,
        refine=None if method == "none" else method,
        mutual=recipe.matching.mutual,
        restarts=recipe.refinement.restarts,
        restart_floor=restart_floor(recipe.gate.min_confidence),
        min_confidence=recipe.gate.min_confidence,
        seed=recipe.seed,
        confidence_model=recipe.features.kind,
        structure_check=recipe.matching.turns is True,
    )


class RegistrationResult(NamedTuple):
    """Outcome of :func:`register_clouds`.

    Attributes:
        T_tgt_src: ``(4, 4)`` float64.
        num_correspondences: correspondences the estimator saw.
        num_inliers: correspondences within the inlier threshold under ``T_tgt_src``.
        inlier_ratio: ``num_inliers / num_correspondences``.
        confidence: the calibrated probability in [0, 1] that ``T_tgt_src`` is right
            (:func:`byoc_cli.pipeline.confidence.probability_right` of ``cues``; 0 when fewer
            than 3 inliers).
        overlap: share of the kept source points that land next to a kept target point.
        num_points_src, num_points_tgt: kept (voxelised) points of each cloud.
        inlier_threshold: in the units of the points.
        timings: seconds per stage.
        cues: what the run knows about its own result, unit-free, for
            :func:`byoc_cli.pipeline.confidence.probability_right`: ``inlier_share``
            (ratio-weighted), ``inlier_ratio``, ``inliers`` (count), ``overlap``,
            ``coarse_inlier_ratio`` (of the robust fit before refinement), ``fitness``,
            ``rmse`` (voxels), ``rank`` and ``conditioning`` of the refinement (1.0, 0.0, 6 and
            1.0 without one),
            ``shift_deg`` and ``shift_voxels``: how far refinement moved the robust fit.
    """

    T_tgt_src: torch.Tensor
    num_correspondences: int
    num_inliers: int
    inlier_ratio: float
    confidence: float
    overlap: float
    num_points_src: int
    num_points_tgt: int
    inlier_threshold: float
    timings: dict[str, float]
    cues: dict[str, float] = {}  # noqa: RUF012 (a NamedTuple default, never mutated)


@dataclass
class _Timer:
    timings: dict[str, float] = field(default_factory=dict)

    def __call__(self, name: str, start: float) -> float:
        now = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + now - start
        return now


def sample_subset(n: int, max_points: int, generator: torch.Generator) -> torch.Tensor | None:
    """A sorted seeded random subset of ``range(n)`` of size ``max_points`` (None = all)."""
    if max_points <= 0 or n <= max_points:
        return None
    return torch.randperm(n, generator=generator)[:max_points].sort().values


def _subset(cloud: CloudFeatures, idx: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    if idx is None:
        return cloud.points, cloud.feats
    return cloud.points[idx], cloud.feats[idx]


def estimate_transform(
    src: CloudFeatures,
    tgt: CloudFeatures,
    config: RegisterConfig,
    voxel_size: float,
    clouds: tuple[torch.Tensor, torch.Tensor] | None = None,
    refine_voxel: float | None = None,
    parallel: Parallel | None = None,
    scan_lines: bool = False,
) -> RegistrationResult:
    """Match two featured clouds and fit ``T_tgt_src`` (no I/O, no feature extraction).

    ``clouds``: the full-resolution ``(N, 3)``, ``(M, 3)`` points that ``"multiscale"``
    refinement runs on (None: the kept points); ``refine_voxel``: the voxel its levels scale
    with (None: ``voxel_size``); ``parallel``: runs independent pieces of the matching and
    the refinement side by side (:func:`byoc_cli.threads.side_by_side`; None: in turn; the
    result is the same bytes).

    ``scan_lines``: the clouds are sampled along lines fixed to the sensor (a spinning LiDAR's
    rings: :attr:`byoc_cli.pipeline.scale.VoxelChoice.scan_lines`), in the sensor's frame.
    Such lines match themselves where the sensor did not move, so a result that is
    identity-like (:func:`identity_like`: the source origin lands within the refinement's
    inlier distance, ``inlier_factor * refine_voxel``, of the target origin, whatever the
    rotation about it; the refinement pulls a match of the lines onto the lines, where they
    meet point for point) is suspect: the correspondences it explains (within the feature
    inlier threshold) are set aside and the rest are fitted again (:func:`_second_try`). A
    second result that moves the origin by the feature inlier threshold at least (a motion
    the features tell from the identity) and reaches ``config.min_confidence`` replaces it (a
    sensor that did not move leaves no such second motion: its result stays); the result's
    ``timings`` then hold ``second_try``.
    """
    timer = _Timer()
    start = time.perf_counter()
    generator = torch.Generator().manual_seed(config.seed)
    points_src, feats_src = _subset(
        src, sample_subset(len(src.points), config.max_points, generator)
    )
    points_tgt, feats_tgt = _subset(
        tgt, sample_subset(len(tgt.points), config.max_points, generator)
    )
    corr = ratio_test_correspondences(
        feats_src,
        feats_tgt,
        k=config.num_correspondences,
        chunk_size=config.chunk_size,
        parallel=parallel,
        mutual=config.mutual,
    )
    if corr.src_idx.numel() < 3:
        raise RegistrationError(f"only {corr.src_idx.numel()} correspondences (need 3)")
    p = points_src[corr.src_idx].to(torch.float64)
    q = points_tgt[corr.tgt_idx].to(torch.float64)
    w = corr.weight.detach().to(torch.float64)
    timer("match", start)

    full = clouds if clouds is not None else (src.points, tgt.points)
    solver = Solver(src, tgt, full, voxel_size, refine_voxel or voxel_size, config, parallel)
    refinement, verdict = solver.solve((p, q, w), (p, q, w), generator, timer)
    if scan_lines and identity_like(refinement.T_tgt_src, solver.still):
        start = time.perf_counter()
        second = _second_try(solver, (p, q, w), refinement.T_tgt_src, generator)
        timer("second_try", start)
        if second is not None:
            refinement, verdict = second
    T = refinement.T_tgt_src
    cues, confidence, num_inliers, overlap = verdict
    return RegistrationResult(
        T_tgt_src=T,
        num_correspondences=int(p.shape[0]),
        num_inliers=num_inliers,
        inlier_ratio=num_inliers / p.shape[0],
        confidence=confidence,
        overlap=overlap,
        num_points_src=int(src.points.shape[0]),
        num_points_tgt=int(tgt.points.shape[0]),
        inlier_threshold=solver.threshold,
        timings=timer.timings,
        cues=cues,
    )


def identity_like(T: torch.Tensor, threshold: float) -> bool:
    """Whether ``T (4, 4)`` leaves the origin within ``threshold`` of itself
    (``|t| < threshold``), whatever its rotation: what lines fixed to a sensor at the origin
    support when they match themselves (a spinning LiDAR's rings are circles about it)."""
    return float(torch.linalg.vector_norm(T[:3, 3])) < threshold


def _second_try(
    solver: Solver, correspondences, T: torch.Tensor, generator: torch.Generator
) -> tuple[Refinement, Verdict] | None:
    """The fit of the correspondences ``(p, q, w)`` that the identity-like ``T (4, 4)`` does
    not explain (residual at or above the feature inlier threshold), judged on all of them;
    None when fewer than 3 are left, the fit fails, its result leaves the origin within the
    feature inlier threshold (identity-like at the features' scale) or is below
    ``min_confidence``."""
    p, q, w = correspondences
    rest = torch.linalg.vector_norm(apply_transform(T, p) - q, dim=1) >= solver.threshold
    if int(rest.sum()) < 3:
        return None
    try:
        refinement, verdict = solver.solve(
            (p[rest], q[rest], w[rest]), correspondences, generator, _Timer()
        )
    except RegistrationError:
        return None
    if (
        identity_like(refinement.T_tgt_src, solver.threshold)
        or verdict.confidence < solver.config.min_confidence
    ):
        return None
    return refinement, verdict


def register_clouds(
    points_src: torch.Tensor,
    points_tgt: torch.Tensor,
    extractor: FeatureExtractor,
    config: RegisterConfig | None = None,
    labels: tuple[str, str] = ("source", "target"),
) -> RegistrationResult:
    """Register ``points_src`` onto ``points_tgt``.

    Args:
        points_src: ``(N, 3)`` source points (metres).
        points_tgt: ``(M, 3)`` target points (metres).
        extractor: computes per-point features (voxelises first).
        config: settings; defaults to :class:`RegisterConfig()`.
        labels: how errors name the two clouds (their file names in the CLI).

    Returns:
        :class:`RegistrationResult` whose ``timings`` also hold ``features_src`` and
        ``features_tgt``.

    Raises:
        RegistrationError: a cloud has fewer than 3 voxels, is smaller than a voxel or
            collinear; no correspondences; no transform could be fitted.
    """
    config = config or RegisterConfig()
    start = time.perf_counter()
    src = extractor(points_src, label=labels[0])
    t_src = time.perf_counter()
    tgt = extractor(points_tgt, label=labels[1])
    t_tgt = time.perf_counter()
    result = estimate_transform(
        src, tgt, config, extractor.voxel_size, clouds=(points_src, points_tgt)
    )
    timings = {"features_src": t_src - start, "features_tgt": t_tgt - t_src, **result.timings}
    timings["total"] = time.perf_counter() - start
    return result._replace(timings=timings)
