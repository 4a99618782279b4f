"""One featured pair through the register engine's middle stages: correspondences, the
robust fit, the refinement and the judgement
(:func:`byoc_cli.pipeline.register.estimate_transform`), handed out as a
:class:`~byoc_cli.pipeline.results.Registration` in the input's coordinates and units."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from byoc_cli.errors import RegistrationError
from byoc_cli.pipeline.results import Features, Registration

if TYPE_CHECKING:
    from byoc_cli.pipeline.recipe import RegistrationRecipe


class Scans(NamedTuple):
    """What a pair's clouds are, beyond their features (:func:`match_pair`).

    Attributes:
        scan_lines: a cloud is sampled along lines fixed to its sensor (an identity-like
            result is fitted again without the correspondences it explains; :func:`scan_lines`).
        rooms: panoramas larger than the trained range
            (:func:`~byoc_cli.pipeline.fallback.large_panoramas`): where they are rooms, the
            structure check turns their results back
            (:attr:`~byoc_cli.pipeline.register.RegisterConfig.turn_rooms`).
    """

    scan_lines: bool = False
    rooms: bool = False


#: clouds that are neither (depth frames, fragments, objects)
PLAIN = Scans()


def match_pair(
    src: Features,
    tgt: Features,
    recipe: RegistrationRecipe,
    refine_clouds: tuple[Any, Any] | None,
    *,
    features: str,
    weights_sha256: str | None,
    parallel: Any = None,
    scans: Scans = PLAIN,
) -> Registration:
    """Register two featured clouds with ``recipe``: ratio-test matches, the robust fit,
    the multiscale refinement on ``refine_clouds`` (their
    :class:`~byoc_cli.pipeline.refine_levels.RefineCloud`; None: the kept points), the cues
    and the confidence; ``passed`` by the recipe's gate.

    Args:
        src, tgt: features of the same kind, voxel and scale, each in its local frame about
            its ``origin``.
        features, weights_sha256: the extractor that ran (the report's).
        parallel: runs independent pieces side by side (None: in turn).
        scans: what the clouds are (:class:`Scans`).

    Returns:
        the registration, ``T_tgt_src`` in input coordinates (origins added back) and units
        (``scale`` divided out).

    Raises:
        RegistrationError: no correspondences, or no transform could be fitted.
    """
    from byoc_cli.pipeline.register import estimate_transform, register_config

    config = register_config(recipe)
    if scans.rooms:
        config = dataclasses.replace(config, turn_rooms=True)
    result = estimate_transform(
        _local(src),
        _local(tgt),
        config,
        src.voxel_size,
        refine_clouds,
        refine_voxel=src.refine_voxel,
        parallel=parallel,
        scan_lines=scans.scan_lines,
    )
    T = about_origins(result.T_tgt_src.numpy(), src.origin, tgt.origin)
    T[:3, 3] /= src.scale  # back to the input units: a transform of s * x has t / s
    return Registration(
        T_tgt_src=T,
        confidence=result.confidence,
        passed=result.confidence >= recipe.gate.min_confidence,
        num_inliers=result.num_inliers,
        num_correspondences=result.num_correspondences,
        inlier_ratio=result.inlier_ratio,
        overlap=result.overlap,
        num_points_src=result.num_points_src,
        num_points_tgt=result.num_points_tgt,
        inlier_threshold=result.inlier_threshold,
        voxel_size=src.voxel_size,
        features=features,
        estimator=recipe.fitting.estimator,
        refine=recipe.refinement.method,
        max_points=config.max_points,
        num_correspondences_per_direction=config.num_correspondences,
        seed=recipe.seed,
        weights_sha256=weights_sha256,
        timings=dict(result.timings),
        cues=dict(result.cues),
        recipe=recipe.as_dict(),
    )


def _local(f: Features):
    """The :class:`~byoc_cli.pipeline.features.CloudFeatures` of ``f`` in its local frame."""
    import torch

    from byoc_cli.pipeline.features import CloudFeatures

    return CloudFeatures(
        torch.from_numpy(f.points if f.origin is None else f.points - f.origin),
        torch.from_numpy(f.feats),
        torch.from_numpy(f.point_index),
        torch.empty(0, 3, dtype=torch.int64),  # voxel coordinates: unused by matching
    )


def about_origins(
    T_local: np.ndarray, origin_src: np.ndarray | None, origin_tgt: np.ndarray | None
) -> np.ndarray:
    """``(4, 4)`` float64 the transform in input coordinates of ``T_local (4, 4)``, which
    maps the source's local points (input minus ``origin_src``) into the target's (input
    minus ``origin_tgt``; None: zeros): ``x_tgt = R (x_src - o_src) + t + o_tgt``."""
    T = np.array(T_local, dtype=np.float64)
    if origin_src is not None:
        T[:3, 3] -= T[:3, :3] @ origin_src
    if origin_tgt is not None:
        T[:3, 3] += origin_tgt
    return T


def scan_lines(made: Any, src: Features, tgt: Features) -> bool:
    """Whether a cloud of the pair is sampled along lines with its sensor at the origin
    (:attr:`~byoc_cli.pipeline.scale.CloudScale.line_voxel`, from ``made.cloud_scale``;
    ``made``: the :class:`~byoc_cli.pipeline.featurizer.Featurizer`): with an auto voxel and
    both clouds at hand, neither registered about another origin (a georeferenced scan's
    origin is not its sensor's)."""
    if not made.auto_voxel or src.cloud is None or tgt.cloud is None:
        return False
    if src.origin is not None or tgt.origin is not None:
        return False
    try:
        return any(
            made.cloud_scale(f.cloud, label).line_voxel > 0
            for f, label in ((src, "source"), (tgt, "target"))
        )
    except RegistrationError:  # too few points to read a scale from: no lines to tell
        return False


def same_voxel(made: Any, src: Features, tgt: Features) -> tuple[Features, Features]:
    """With an auto voxel of ``made`` (a :class:`~byoc_cli.pipeline.featurizer.Featurizer`),
    two clouds extracted one at a time may have chosen different voxels: both are extracted
    again at the pair's (from their ``cloud``). Otherwise ``(src, tgt)`` as they are."""
    same = (src.voxel_size, src.refine_voxel) == (tgt.voxel_size, tgt.refine_voxel)
    if same or not made.auto_voxel or src.cloud is None or tgt.cloud is None:
        return src, tgt
    if src.features != made.features or tgt.features != made.features:
        return src, tgt
    choice = made.choose_voxel(src.cloud, tgt.cloud)
    voxel = (choice.voxel_size, choice.refine_voxel)
    return (
        made.extract_points(src.cloud, src.scale, "source", *voxel, choice.keep_of(0)),
        made.extract_points(tgt.cloud, tgt.scale, "target", *voxel, choice.keep_of(1)),
    )
