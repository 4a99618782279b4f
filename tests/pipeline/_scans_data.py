"""Fragments of a real posed sequence for the register-scans tests (fused at test time)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from byoc_cli.io.rgbd import discover_sequences
from byoc_cli.pipeline.fragments import fuse_fragment

#: the first 75 frames of tum_fr1_desk_full (about 5 s), 25 frames per fragment, 1 cm TSDF
FRAMES_PER_FRAGMENT = 25
NUM_FRAGMENTS = 3
TSDF_VOXEL = 0.01


def desk_fragments(shared_data: Path) -> tuple[list[np.ndarray], np.ndarray]:
    """``(clouds, poses)``: fragments in their first camera's frame and their ground truth
    ``T_frag0_fragk (K, 4, 4)`` (the first fragment is the world)."""
    sequence = discover_sequences(shared_data / "rgbd" / "tum_fr1_desk_full", require_poses=True)[0]
    gt = np.stack([sequence.pose(i) for i in range(FRAMES_PER_FRAGMENT * NUM_FRAGMENTS)])
    clouds, poses = [], []
    for f in range(NUM_FRAGMENTS):
        frames = list(range(f * FRAMES_PER_FRAGMENT, (f + 1) * FRAMES_PER_FRAGMENT))
        clouds.append(fuse_fragment(sequence, frames, gt[frames], voxel_size=TSDF_VOXEL))
        poses.append(np.linalg.inv(gt[0]) @ gt[frames[0]])
    return clouds, np.stack(poses)


def pose_errors(poses: list, gt: np.ndarray) -> tuple[float, float]:
    """Median rotation (deg) and translation (m) error of ``poses`` against ``gt``."""
    from byoc_cli.pipeline.posegraph import transform_difference

    errors = np.array([transform_difference(g, p) for p, g in zip(poses, gt, strict=True)])
    return float(np.median(errors[1:, 0])), float(np.median(errors[1:, 1]))
