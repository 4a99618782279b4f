"""Geometry primitives: rigid transforms (``T_tgt_src``, 4x4 on column vectors) and voxelisation.

Conventions used throughout byoc-cli:

* one cloud is ``points (N, 3)``; features ``feats (N, C)``; indices are int64;
* a rigid transform ``T_tgt_src`` is a 4x4 matrix on column vectors that maps a point
  of the source frame into the target frame: ``x_tgt = R @ x_src + t``. Points are
  stored as rows, so code applies ``points @ R.T + t``.
"""

from byoc_cli.geometry.transforms import (
    apply_transform,
    compose,
    correspondence_inlier_ratio,
    invert_transform,
    make_transform,
    random_rigid_transform,
    rotation_error_deg,
    translation_error,
)
from byoc_cli.geometry.voxel import VoxelGrid, voxelize

__all__ = [
    "VoxelGrid",
    "apply_transform",
    "compose",
    "correspondence_inlier_ratio",
    "invert_transform",
    "make_transform",
    "random_rigid_transform",
    "rotation_error_deg",
    "translation_error",
    "voxelize",
]
