"""The local registration of a pair from an initial pose (``--init``): no encoder, no matching.

A guess of ``T_tgt_src`` (odometry, a robot, GNSS/IMU, a scanner's station, the previous
result) that is off by a few degrees and decimetres is refined where it is:

1. **Coarse pass** (:func:`align_coarse`): plane-to-plane ICP
   (:func:`~byoc_cli.fitting.plane_to_plane.plane_to_plane_step`) on the voxel averages and
   normals of a :class:`~byoc_cli.pipeline.refine_levels.RefineCloud` at
   :data:`COARSE_BASE` refinement voxels ``v``: levels ``(6v, 12v)``, ``(3v, 6v)``,
   ``(2.4v, 3.6v)`` (voxel, correspondence distance). At depth-camera scale (``v`` = 2.5 cm)
   its first level pairs points 30 cm apart, and it reaches guesses 10 deg and 30 cm off
   (the points 1.5 m from the centroid are 55 cm off) over a few iterations; a base of 4 or
   8 voxels brought 33 of 56 such guesses on the benchmark's pairs within 5 deg and 10 cm of
   the truth, 6 voxels 36 (the others: pairs with almost no overlap).
2. **Refinement**: the multiscale point-to-plane refinement of every registration
   (:func:`~byoc_cli.pipeline.refine.refine_multiscale`, levels ``(v, 2v)`` to
   ``(0.4v, 0.6v)``), from the coarse pass's end and (on :data:`PROBE_POINTS` points) from the
   guess itself; the latter is kept (and refined on all points) unless the former ends
   elsewhere with a clearly better fit (:data:`SWITCH_FITNESS`).
3. **Trust region** (:class:`TrustRegion`): the correction ``T_result @ inv(T_init)``, as its
   rotation angle and the distance the source's centroid moved (:func:`correction`), may not
   exceed ``--max-correction`` (default :data:`MAX_CORRECTION_DEG` and
   :data:`MAX_CORRECTION_VOXELS` refinement voxels, 0.5 m at depth-camera scale); a result
   beyond it does not pass.
4. **Confidence**: its own calibrated probability
   (:mod:`byoc_cli.pipeline.local_confidence`) from the fit, the coarse pass, the
   conditioning and the size of the correction.

The ``v`` is the pair's refinement voxel (``--voxel-size auto`` still runs: it needs no
features). Clouds are registered about their local frames as the global path does
(:func:`byoc_cli.geometry.sampling.local_frame`), and ``T`` is in the input's units.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from byoc_cli.pipeline.local_confidence import local_probability
from byoc_cli.pipeline.pair import about_origins
from byoc_cli.pipeline.results import Registration

if TYPE_CHECKING:  # torch is imported where it is used: the API imports this module
    import torch

    from byoc_cli.pipeline.refine_levels import RefineCloud

#: the coarse pass's levels are a :class:`RefineCloud`'s at this many refinement voxels
COARSE_BASE = 6.0
#: source points per coarse level at most, and Gauss-Newton steps per level at most
COARSE_POINTS = 3000
COARSE_ITERATIONS = 20
#: a coarse level stops when a step moves less than this (radians, and level voxels)
COARSE_TOLERANCE = 1e-4
#: fewest pairs within reach for a coarse step (fewer: the level is skipped)
COARSE_MIN_PAIRS = 12
#: the refinement from the coarse pass's end replaces the one from the guess itself when it
#: lies elsewhere (beyond SAME_DEG or SAME_VOXELS refinement voxels) and fits better by this
#: (in a scene of a few planes the data can favour a pose 15 deg from the truth by 0.03 of
#: fitness: a guess the refinement confirms is the better witness)
SWITCH_FITNESS = 0.05
#: source points per level of the refinement from the guess itself (refined again on all of
#: them when it is kept)
PROBE_POINTS = 500
#: source points per level of the refinement reported
FINAL_POINTS = 5000
SAME_DEG, SAME_VOXELS = 1.0, 1.0
#: the default trust region: the rotation of the correction, in degrees, and the distance the
#: source's centroid moves, in refinement voxels (chosen from ``benchmarks/init.py``: guesses
#: up to 15 deg and 40 cm off come back right; docs/poses.md)
MAX_CORRECTION_DEG = 20.0
MAX_CORRECTION_VOXELS = 20.0


class TrustRegion(NamedTuple):
    """How far a local registration may move the source from its initial pose.

    Attributes:
        rotation_deg: the rotation angle of ``T_result @ inv(T_init)`` at most, in degrees.
        translation: the distance the source's centroid may move, in the input's units
            (those of ``T``); None: :data:`MAX_CORRECTION_VOXELS` refinement voxels.
    """

    rotation_deg: float = MAX_CORRECTION_DEG
    translation: float | None = None

    def resolved(self, voxel: float, scale: float) -> TrustRegion:
        """This region with its translation in input units (``voxel`` in the points' units,
        ``scale`` the points' factor over the input's)."""
        if self.translation is not None:
            return self
        return self._replace(translation=MAX_CORRECTION_VOXELS * voxel / scale)

    def holds(self, moved: Correction) -> bool:
        """Whether ``moved`` (of the same units) lies inside."""
        return moved.rotation_deg <= self.rotation_deg and moved.translation <= self.translation


#: what ``init_mode`` takes: the local registration from the guess, or the global one
#: checked against it
INIT_MODES = ("local", "global")
#: tolerances of a guess's last row and of its rotation's orthonormality
_LAST_ROW_TOL, _ORTHONORMAL_TOL = 1e-6, 1e-3


class InitialPose(NamedTuple):
    """A guess of ``T_tgt_src`` and what to do with it.

    Attributes:
        T: ``(4, 4)`` float64, in the input's units (as ``T`` is written).
        trust: the :class:`TrustRegion` of the result around it.
        mode: one of :data:`INIT_MODES`.
    """

    T: np.ndarray
    trust: TrustRegion = TrustRegion()
    mode: str = "local"

    @classmethod
    def of(cls, init: Any, max_correction: Any = None, mode: str = "local") -> InitialPose:
        """An :class:`InitialPose` of the API's arguments: ``init`` a ``(4, 4)`` rigid
        transform, ``max_correction`` None (the defaults), a :class:`TrustRegion` or
        ``(degrees, distance)`` (distance None: the default).

        Raises:
            ValueError: ``init`` is not a finite rigid ``(4, 4)`` transform, a bound that is
                not a positive number, an unknown ``mode``.
        """
        if mode not in INIT_MODES:
            raise ValueError(f"init_mode must be one of {INIT_MODES}, got {mode!r}")
        T = np.array(init, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"init must be a finite (4, 4) transform, got shape {T.shape}")
        R = T[:3, :3]
        if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > _LAST_ROW_TOL:
            raise ValueError(f"init's last row must be 0 0 0 1, got {T[3].tolist()}")
        if np.abs(R.T @ R - np.eye(3)).max() > _ORTHONORMAL_TOL or np.linalg.det(R) <= 0:
            raise ValueError("init's rotation is not a rotation (R^T R != I or det R <= 0)")
        if max_correction is None:
            trust = TrustRegion()
        elif isinstance(max_correction, TrustRegion):
            trust = max_correction
        else:
            deg, dist = max_correction
            trust = TrustRegion(float(deg), None if dist is None else float(dist))
        bounds = [trust.rotation_deg] + ([] if trust.translation is None else [trust.translation])
        if not all(math.isfinite(b) and b > 0 for b in bounds):
            raise ValueError(f"max_correction must be positive numbers, got {tuple(trust)}")
        return cls(T, trust, mode)


class Correction(NamedTuple):
    """How far a result lies from a pose: the rotation angle of ``T_result @ inv(T_init)``
    in degrees and the distance the source's centroid moves between them (units of ``T``)."""

    rotation_deg: float
    translation: float

    def as_dict(self) -> dict[str, float]:
        return {"rotation_deg": self.rotation_deg, "translation": self.translation}


def correction(T_result: np.ndarray, T_init: np.ndarray, centroid: np.ndarray) -> Correction:
    """The :class:`Correction` from ``T_init (4, 4)`` to ``T_result (4, 4)`` for a source
    whose centroid is ``centroid (3,)`` (source coordinates)."""
    from byoc_cli.pipeline.posegraph import rotation_angle_deg

    angle = rotation_angle_deg((T_result @ np.linalg.inv(T_init))[:3, :3])
    moved = T_result[:3, :3] @ centroid + T_result[:3, 3]
    start = T_init[:3, :3] @ centroid + T_init[:3, 3]
    return Correction(angle, float(np.linalg.norm(moved - start)))


def align_coarse(src: RefineCloud, tgt: RefineCloud, T: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Plane-to-plane ICP of ``src`` onto ``tgt`` from ``T (4, 4)`` over their levels
    (coarse to fine, each up to :data:`COARSE_ITERATIONS` steps on at most
    :data:`COARSE_POINTS` source points, pairs within the level's correspondence distance).

    Returns:
        ``(T (4, 4) float64, fitness)``: the share of the last level's source points with a
        target point within its distance (0.0 when no level ran; ``T`` as given).
    """
    import torch
    from pykdtree.kdtree import KDTree

    from byoc_cli.fitting.plane_to_plane import plane_to_plane_step
    from byoc_cli.pipeline.posegraph import rotation_angle_deg

    T = T.detach().to(device="cpu", dtype=torch.float64).numpy().copy()
    fitness = 0.0
    for level, (size, dist, _) in enumerate(src.levels):
        p, n_p = (x.numpy() for x in src.oriented_source(level, COARSE_POINTS))
        q, n_q, _ = tgt.target(level)
        if len(p) < COARSE_MIN_PAIRS or len(q) < COARSE_MIN_PAIRS:
            break
        q, n_q = q.numpy(), n_q.numpy()
        tree = KDTree(q)
        for _ in range(COARSE_ITERATIONS):  # in numpy, as the refinement's steps
            moved, turned = p @ T[:3, :3].T + T[:3, 3], n_p @ T[:3, :3].T
            d, j = tree.query(moved, k=1, distance_upper_bound=dist)
            ok = np.isfinite(d) & (j < len(q))
            fitness = float(np.count_nonzero(ok)) / len(ok)
            if int(np.count_nonzero(ok)) < COARSE_MIN_PAIRS:
                break
            j = j[ok].astype(np.int64)
            step = plane_to_plane_step(moved[ok], turned[ok], q[j], n_q[j]).T.numpy()
            T = step @ T
            angle = math.radians(rotation_angle_deg(step[:3, :3]))
            if angle < COARSE_TOLERANCE and float(np.linalg.norm(step[:3, 3])) < (
                COARSE_TOLERANCE * size
            ):
                break
    return torch.from_numpy(T), fitness


class LocalPair(NamedTuple):
    """A pair read and measured for the local stage.

    Attributes:
        points: the source's and the target's ``(N, 3)`` float64 points (input times ``scale``).
        voxel: the refinement voxel ``v`` (points' units).
        scale: the points' factor over the input's units (``T`` is divided back by it).
        voxel_choice: the auto voxel's :meth:`~byoc_cli.pipeline.scale.VoxelChoice.as_dict`
            (None: an explicit voxel).
    """

    points: tuple[np.ndarray, np.ndarray]
    voxel: float
    scale: float
    voxel_choice: dict | None = None


def register_local(
    made: Any, pair: LocalPair, T_init: np.ndarray, trust: TrustRegion, timings: dict
) -> Registration:
    """The local registration of ``pair`` from ``T_init (4, 4)`` (input units) with ``made``,
    a :class:`~byoc_cli.pipeline.registrar.Registrar` (its refinement clouds, frames and
    recipe): the coarse pass, the refinement, the cues, the confidence and the trust region
    (the module docstring). ``passed``: inside ``trust`` and at or above the recipe's gate.

    ``timings`` (seconds of the stages before, ``load`` and ``scale``) are extended with
    ``coarse`` (its levels built on first use), ``refine``, ``verify`` and ``total``.
    """
    import torch

    from byoc_cli.pipeline.refine import refine_multiscale

    start = time.perf_counter()
    src_points, v, scale = pair.points[0], pair.voxel, pair.scale
    frames = [made.frame(points) for points in pair.points]
    origins = [f.origin if f.moved else None for f in frames]
    T0 = np.array(T_init, dtype=np.float64)
    T0[:3, 3] *= scale
    T_local = _to_local(T0, *origins)
    fine = [made.refinement_cloud(points, v) for points in pair.points]
    coarse = [
        made.refinement_cloud(points, COARSE_BASE * v, within=cloud)
        for points, cloud in zip(pair.points, fine, strict=True)
    ]
    start_local = torch.from_numpy(T_local)
    T_coarse, coarse_fitness = align_coarse(*coarse, start_local)
    now = _lap(timings, "coarse", start)
    # the coarse pass's end refined on all points, the guess itself on a few: a guess the
    # refinement confirms is kept unless the other ends elsewhere and fits clearly better
    far = refine_multiscale(*fine, T_coarse, v, max_source_points=FINAL_POINTS)
    near = refine_multiscale(*fine, start_local, v, max_source_points=PROBE_POINTS)
    same = _same_place(near.T_tgt_src, far.T_tgt_src, v)
    keep_near = not same and far.fitness <= near.fitness + SWITCH_FITNESS
    if keep_near:
        refined = refine_multiscale(*fine, near.T_tgt_src, v, max_source_points=FINAL_POINTS)
    else:
        refined = far
    other = far if keep_near else near
    now = _lap(timings, "refine", now)
    cues = _cues(fine, refined, T_coarse, coarse_fitness, T_local, v)
    cues["agree"] = 1.0 if same else 0.0
    cues["other_gain"] = other.fitness - (near.fitness if keep_near else far.fitness)
    confidence = local_probability(cues)
    T = about_origins(refined.T_tgt_src.numpy(), *origins)
    T[:3, 3] /= scale
    centroid = frames[0].centroid(src_points) / scale  # a stray point far away moves it not
    moved = correction(T, np.asarray(T_init, dtype=np.float64), centroid)
    region = trust.resolved(v, scale)
    inside = region.holds(moved)
    gate = made.recipe.gate.min_confidence
    _lap(timings, "verify", now)
    timings["total"] = timings.get("load", 0.0) + timings.get("scale", 0.0)
    timings["total"] += time.perf_counter() - start
    last = len(fine[0].levels) - 1
    used = len(fine[0].source(last, FINAL_POINTS))
    return Registration(
        T_tgt_src=T,
        confidence=confidence,
        passed=inside and confidence >= gate,
        num_inliers=round(refined.fitness * used),
        num_correspondences=used,
        inlier_ratio=refined.fitness,
        overlap=cues["overlap"],
        num_points_src=len(fine[0].average(last)),
        num_points_tgt=len(fine[1].average(last)),
        inlier_threshold=fine[0].levels[last][1],
        voxel_size=v,
        features="none",
        estimator="none",
        refine="multiscale",
        max_points=made.recipe.matching.max_points,
        num_correspondences_per_direction=0,
        seed=made.recipe.seed,
        weights_sha256=None,
        timings=timings,
        voxel_choice=pair.voxel_choice,
        cues=cues,
        recipe=made.recipe.as_dict(),
        path="local",
        init={
            "T_init": np.asarray(T_init, dtype=np.float64).tolist(),
            "correction": moved.as_dict(),
            "trust_region": {
                "rotation_deg": region.rotation_deg,
                "translation": region.translation,
            },
            "inside_trust_region": inside,
        },
    )


def _same_place(T_a, T_b, voxel: float) -> bool:
    """Whether ``T_a`` and ``T_b (4, 4)`` lie within SAME_DEG and SAME_VOXELS voxels."""
    import torch

    from byoc_cli.pipeline.posegraph import rotation_angle_deg

    D = (torch.linalg.inv(T_a) @ T_b).numpy()
    return (
        rotation_angle_deg(D[:3, :3]) < SAME_DEG
        and float(np.linalg.norm(D[:3, 3])) < SAME_VOXELS * voxel
    )


def _cues(fine, refined, T_coarse, coarse_fitness, T_local, v) -> dict[str, float]:
    """What the local confidence reads (:data:`~byoc_cli.pipeline.local_confidence.FEATURES`)."""
    import torch

    from byoc_cli.geometry.voxel import near_occupied
    from byoc_cli.pipeline.posegraph import rotation_angle_deg

    T = refined.T_tgt_src
    p = fine[0].source(0)
    moved = p @ T[:3, :3].T + T[:3, 3]
    overlap = float(near_occupied(moved, fine[1].average(0), v).float().mean())
    shift = T @ torch.linalg.inv(T_coarse)
    centroid = p.mean(0)
    moved_by = np.asarray(T_local)
    start = torch.from_numpy(moved_by[:3, :3]) @ centroid + torch.from_numpy(moved_by[:3, 3])
    end = T[:3, :3] @ centroid + T[:3, 3]
    return {
        "fitness": refined.fitness,
        "rmse": refined.rmse,
        "rank": float(refined.rank),
        "conditioning": refined.conditioning,
        "coarse_fitness": coarse_fitness,
        "overlap": overlap,
        "shift_deg": rotation_angle_deg(shift[:3, :3].numpy()),
        "shift_voxels": float(torch.linalg.vector_norm(shift[:3, 3])) / v,
        "correction_deg": rotation_angle_deg(T[:3, :3].numpy() @ moved_by[:3, :3].T),
        "correction_voxels": float(torch.linalg.vector_norm(end - start)) / v,
    }


def _to_local(T: np.ndarray, origin_src, origin_tgt) -> np.ndarray:
    """``T (4, 4)`` in input coordinates as the map between the local frames (the inverse of
    :func:`~byoc_cli.pipeline.pair.about_origins`)."""
    T = np.array(T, dtype=np.float64)
    if origin_src is not None:
        T[:3, 3] += T[:3, :3] @ origin_src
    if origin_tgt is not None:
        T[:3, 3] -= origin_tgt
    return T


def _lap(timings: dict, stage: str, start: float) -> float:
    now = time.perf_counter()
    timings[stage] = timings.get(stage, 0.0) + now - start
    return now


def check_global(
    made: Any, found: Registration, pair: LocalPair, guess: InitialPose, timings: dict
) -> Registration:
    """``init_mode="global"``: the global registration ``found`` checked against the guess.

    Kept when it lies inside the guess's trust region and passes its gate (``check``:
    ``"agrees"``). Otherwise the local registration from the guess runs and is kept when it
    passes (``"local"``); else ``found`` is kept, not passed when it left the trust region
    (``"disagrees"``; one below its gate stays below it: ``"below gate"``).
    """
    centroid = made.frame(pair.points[0]).centroid(pair.points[0]) / pair.scale
    region = guess.trust.resolved(pair.voxel, pair.scale)
    moved = correction(found.T_tgt_src, guess.T, centroid)
    agrees = region.holds(moved)
    report = {
        "mode": "global",
        "T_init": guess.T.tolist(),
        "correction": moved.as_dict(),
        "trust_region": {"rotation_deg": region.rotation_deg, "translation": region.translation},
        "inside_trust_region": agrees,
        "global": {"confidence": found.confidence, "passed": found.passed},
    }
    if agrees and found.passed:
        return found._replace(init={**report, "check": "agrees"})
    local = register_local(made, pair, guess.T, guess.trust, timings)
    if local.passed:
        timings = {**local.timings, "global": found.timings.get("total", 0.0)}
        return local._replace(init={**report, **local.init, "check": "local"}, timings=timings)
    report["local"] = {"confidence": local.confidence, "passed": False, **local.init}
    if agrees:
        return found._replace(init={**report, "check": "below gate"})
    return found._replace(passed=False, init={**report, "check": "disagrees"})
