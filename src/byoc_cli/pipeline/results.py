"""What the register engine hands out: one cloud's :class:`Features` and one pair's
:class:`Registration` (numpy arrays and numbers; the types of the Python API)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Features(NamedTuple):
    """Per-point features of one cloud (what ``byoc features`` writes).

    Attributes:
        points: ``(M, 3)`` float64 kept points in metres (input coordinates times ``scale``;
            the first input point of each occupied voxel).
        feats: ``(M, C)`` float32 L2-normalised features; ``feats[m]`` describes ``points[m]``.
        point_index: ``(M,)`` int64; ``points[m]`` is input point ``point_index[m]``.
        voxel_size: the voxel size in metres.
        scale: the factor the input coordinates were multiplied by (1.0 = metres already).
        features: ``"byoc"`` or ``"fpfh"``.
        weights_sha256: SHA-256 of the weights file (None for fpfh).
        cloud: ``(N, 3)`` float64 input points in metres, which ``"multiscale"``
            refinement runs on; None (features read back from a file): the kept points. A
            :class:`~byoc_cli.pipeline.registrar.Registrar` keeps what it builds from this
            array (refinement levels, the fallback's features) by its identity for later
            pairs: change a copy, not the array.
        refine_voxel: the voxel the refinement levels scale with (None: ``voxel_size``);
            the auto voxel keeps it below a ``voxel_size`` raised for sparse clouds.
        origin: ``(3,)`` float64 the cloud is registered about
            (:func:`byoc_cli.geometry.sampling.local_frame`: its median point when it lies
            far from the origin, else zeros); None: zeros.
    """

    points: np.ndarray
    feats: np.ndarray
    point_index: np.ndarray
    voxel_size: float
    scale: float
    features: str
    weights_sha256: str | None
    cloud: np.ndarray | None = None
    refine_voxel: float | None = None
    origin: np.ndarray | None = None


class Registration(NamedTuple):
    """One pair's registration (:meth:`~byoc_cli.pipeline.registrar.Registrar.register`).

    Attributes:
        T_tgt_src: ``(4, 4)`` float64, maps source points into the target frame
            (``x_tgt = R x_src + t``, column vectors), in the units of the input.
        confidence: the calibrated probability in [0, 1] that ``T_tgt_src`` is right (within
            5 deg and 10 cm at the features' scale; 0 when fewer than 3 inliers).
        passed: ``confidence`` is at or above the gate, the recipe's ``gate.min_confidence``
            (``byoc register`` exits 3 when it is not).
        num_inliers, num_correspondences, inlier_ratio: the verified correspondences.
        overlap: share of the kept source points that land next to a kept target point.
        num_points_src, num_points_tgt: kept (voxelised) points of each cloud.
        inlier_threshold: in the units of the points (of the input, times ``scale``).
        voxel_size: in the same units.
        features, estimator, refine: what ran (``refine`` is ``"none"`` or ``"multiscale"``).
        max_points, num_correspondences_per_direction, seed: the matching settings.
        weights_sha256: SHA-256 of the weights file (None for fpfh).
        timings: seconds per stage (``features_src``, ``features_tgt``, ``match``, ``fit``,
            ``verify``, ``total``; a stage that was cached reads 0).
        voxel_choice: with ``voxel_size="auto"``, how the voxel was chosen
            (:meth:`byoc_cli.pipeline.scale.VoxelChoice.as_dict`); None otherwise.
        cues: what the confidence is computed from
            (:attr:`byoc_cli.pipeline.register.RegistrationResult.cues`).
        fallback: when the learned features' confidence fell below the registrar's
            ``fallback_below`` and FPFH ran too: ``features``, ``used`` (the result is
            FPFH's), ``learned_confidence``, ``confidence`` (FPFH's; None when it could not
            register) and ``seconds``; None when no fallback ran.
        recipe: the recipe that ran
            (:meth:`byoc_cli.pipeline.recipe.RegistrationRecipe.as_dict`; the fallback's
            when its result is kept).
        path: ``"global"`` (features, matching, robust fit, refinement) or ``"local"`` (the
            refinement from an initial pose, :mod:`byoc_cli.pipeline.local`: ``features`` and
            ``estimator`` read ``"none"``, the inliers are the refinement's finest level).
        init: with an initial pose: ``T_init``, the ``correction`` of the result from it
            (``rotation_deg``, ``translation`` of the source's centroid, input units), the
            ``trust_region`` and ``inside_trust_region``; with ``init_mode="global"`` also
            ``mode`` and ``check`` (:func:`byoc_cli.pipeline.sequence.register_from_init`).
            None without one.
        features_choice: with learned features, an auto voxel and the FPFH fallback, which
            features the pair started with and why
            (:meth:`byoc_cli.pipeline.feature_choice.FeaturesChoice.as_dict`): ``"fpfh"`` for a
            smooth pair (when the learned features ran as its second opinion, ``fallback``
            says what they reached: ``features: "byoc"``, ``first_confidence``: FPFH's);
            None otherwise.
        turns: when the learned features were also tried on the source turned about its up
            axis (:mod:`byoc_cli.pipeline.turns`): ``up_axis``, the ``tries`` (each turn's
            ``degrees``, ``confidence`` and ``T_tgt_src``; 0 the first), ``kept_deg`` and
            whether the result is ``ambiguous`` (then it does not pass); None otherwise.
        reproduced: when a smooth pair's FPFH result below the gate was fitted twice more
            (:func:`byoc_cli.pipeline.feature_choice.reproduce`): the ``repeats``, whether they
            ``agree`` (then ``confidence`` is raised) and the ``model_confidence`` before;
            None otherwise.
        retries: when the first result was below the gate and the matching ran again with
            the next seeds (:func:`byoc_cli.pipeline.retries.with_retries`): the
            ``first_confidence`` and ``first_T_tgt_src``, the ``tries`` (``seed``, discounted
            ``confidence``, ``model_confidence``, ``T_tgt_src``), the ``kept_seed`` (None: the
            first result) and the ``seconds``; None otherwise.
        check: when a learned result that passed at low overlap was registered again with
            the next seed (:func:`byoc_cli.pipeline.recheck.with_check`): the check's ``seed``,
            ``model_confidence`` and ``T_tgt_src``, whether it ``agrees``, whether the result
            is ``ambiguous`` (then it does not pass), the ``alternatives`` (both poses with
            their ``seed``, ``confidence`` and ``T_tgt_src``, most confident first), the
            ``kept_seed`` and the ``seconds``; None otherwise.
        visibility: when a passing result was checked for surfaces in the other scan's free
            space (:func:`byoc_cli.pipeline.visibility.with_visibility`): the shares
            ``source_in_target`` and ``target_in_source``, the points ``seen`` of each, the
            larger share ``free_space``, ``max_free_space``, whether the result is
            ``consistent`` (else it does not pass) and the ``seconds``; None otherwise.
    """

    T_tgt_src: np.ndarray
    confidence: float
    passed: bool
    num_inliers: int
    num_correspondences: int
    inlier_ratio: float
    overlap: float
    num_points_src: int
    num_points_tgt: int
    inlier_threshold: float
    voxel_size: float
    features: str
    estimator: str
    refine: str
    max_points: int
    num_correspondences_per_direction: int
    seed: int
    weights_sha256: str | None
    timings: dict[str, float]
    voxel_choice: dict | None = None
    cues: dict[str, float] | None = None
    fallback: dict | None = None
    recipe: dict | None = None
    path: str = "global"
    init: dict | None = None
    features_choice: dict | None = None
    turns: dict | None = None
    reproduced: dict | None = None
    retries: dict | None = None
    check: dict | None = None
    visibility: dict | None = None
