"""TSDF fusion of posed depth frames into one fragment (the 3DMatch recipe).

Every fragment's points are in the camera frame of its FIRST frame. Fusion uses Open3D's
hashed voxel-block TSDF (``open3d.t.geometry.VoxelBlockGrid``); see
:mod:`byoc_cli.pipeline.fragments` for the benchmark built on it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from byoc_cli import limits
from byoc_cli.errors import ShapeError, require_open3d
from byoc_cli.io.rgbd import RGBDSequence

#: Frames per fragment of 3DMatch (at 30 Hz).
DEFAULT_FRAMES_PER_FRAGMENT = 50
#: TSDF voxel of 3DMatch's fragments, metres.
DEFAULT_TSDF_VOXEL = 0.006
#: TSDF truncation distance, metres (Open3D's reconstruction system: 0.04 at ~6 mm voxels).
DEFAULT_SDF_TRUNC = 0.04
#: Depth beyond this is ignored, metres (Open3D's reconstruction system: 3.0).
DEFAULT_DEPTH_TRUNC = 3.0
#: A voxel must be seen by at least this many frames to give a point.
DEFAULT_MIN_OBSERVATIONS = 3
#: Hash-table blocks of 16^3 voxels reserved at first (the table grows when needed).
_BLOCK_RESOLUTION = 16
_INITIAL_BLOCKS = 20_000
_UINT16_MAX = 65535


def _check_positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number, got {value}")
    return value


def _check_poses(poses: np.ndarray, count: int, name: str = "poses_world_cam") -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (count, 4, 4):
        raise ShapeError(f"{name} must be ({count}, 4, 4), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ShapeError(f"{name} has NaN or Inf entries")
    R = poses[:, :3, :3]
    error = np.abs(np.einsum("nki,nkj->nij", R, R) - np.eye(3)).max(initial=0.0)
    bottom = np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(initial=0.0)
    if error > 1e-3 or bottom > 1e-6 or np.any(np.linalg.det(R) < 0):
        raise ShapeError(f"{name} must be rigid transforms")
    return poses


def relative_pose(pose_tgt: np.ndarray, pose_src: np.ndarray) -> np.ndarray:
    """``T_tgt_src = inv(pose_tgt) @ pose_src`` of two camera-to-world poses.

    Args:
        pose_tgt, pose_src: ``(4, 4)`` ``T_world_cam``.

    Returns:
        ``(4, 4)`` float64 mapping points of the source camera frame into the target's.
    """
    pose_tgt = np.asarray(pose_tgt, dtype=np.float64)
    pose_src = np.asarray(pose_src, dtype=np.float64)
    if pose_tgt.shape != (4, 4) or pose_src.shape != (4, 4):
        raise ShapeError(f"poses must be (4, 4), got {pose_tgt.shape} and {pose_src.shape}")
    inverse = np.eye(4)
    inverse[:3, :3] = pose_tgt[:3, :3].T
    inverse[:3, 3] = -pose_tgt[:3, :3].T @ pose_tgt[:3, 3]
    return inverse @ pose_src


def fragment_windows(
    num_frames: int,
    frames_per_fragment: int = DEFAULT_FRAMES_PER_FRAGMENT,
    stride: int | None = None,
) -> list[range]:
    """Frame windows of the fragments: ``range(s, s + N)`` for ``s = 0, M, 2M, ...``.

    Only full windows are kept (a tail shorter than ``N`` frames is dropped).

    Args:
        num_frames: frames of the sequence.
        frames_per_fragment: ``N``, >= 1.
        stride: ``M``, >= 1: a fragment starts every ``M`` frames (None: ``N``, consecutive
            non-overlapping windows).

    Returns:
        The windows in order (empty when ``num_frames < N``).

    Raises:
        ValueError: ``N`` or ``M`` below 1, or ``num_frames`` negative.
    """
    num_frames, size = int(num_frames), int(frames_per_fragment)
    step = size if stride is None else int(stride)
    if num_frames < 0:
        raise ValueError(f"num_frames must be >= 0, got {num_frames}")
    if size < 1 or step < 1:
        raise ValueError(f"frames_per_fragment and stride must be >= 1, got {size} and {step}")
    return [range(s, s + size) for s in range(0, num_frames - size + 1, step)]


# ================================================================== fusion


def _raw_depth(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metres -> uint16 raw units (Open3D's voxel block grid reads integer depth)."""
    raw = np.rint(np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0) * depth_scale)
    raw[(raw < 0) | (raw > _UINT16_MAX)] = 0
    return raw.astype(np.uint16)


def fuse_fragment(
    sequence: RGBDSequence,
    frame_indices: Sequence[int],
    poses_world_cam: np.ndarray,
    *,
    voxel_size: float = DEFAULT_TSDF_VOXEL,
    sdf_trunc: float = DEFAULT_SDF_TRUNC,
    depth_trunc: float = DEFAULT_DEPTH_TRUNC,
    min_observations: int = DEFAULT_MIN_OBSERVATIONS,
) -> np.ndarray:
    """Fuse depth frames into one point cloud in the FIRST frame's camera frame (TSDF).

    Objective: TSDF fusion (Open3D voxel block grid, ``voxel_size`` voxels, truncation
    ``sdf_trunc``) of the depth of ``frame_indices``, each placed by its pose relative to the
    first, ``inv(poses[0]) @ poses[k]``; the points are the zero crossings seen by at least
    ``min_observations`` frames. Poses are passed explicitly, so estimated poses work as well as
    the sequence's ground truth.

    Args:
        sequence: the RGB-D sequence (only depth is read).
        frame_indices: ``F`` positions in ``sequence.frames``; the first defines the frame.
        poses_world_cam: ``(F, 4, 4)`` camera-to-world poses, one per frame index (any
            common world frame).
        voxel_size: TSDF voxel, metres.
        sdf_trunc: truncation distance, metres (> ``voxel_size``).
        depth_trunc: depth beyond this is ignored, metres.
        min_observations: frames (>= 1) that must see a voxel for it to give a point.

    Returns:
        ``(N, 3)`` float32 points in metres, in the first frame's camera frame, sorted by
        x, then y, then z (the same array on every run; N may be 0).

    Raises:
        ShapeError: ``poses_world_cam`` not ``(F, 4, 4)`` rigid, no frame index, or an index
            out of range.
        ValueError: a non-positive size, ``sdf_trunc <= voxel_size``, or
            ``min_observations < 1``.
        FrameError: a depth image cannot be read.
        DependencyError: open3d cannot be imported.
    """
    frames = [int(k) for k in frame_indices]
    if not frames:
        raise ShapeError("frame_indices is empty")
    if min(frames) < 0 or max(frames) >= len(sequence.frames):
        raise ShapeError(f"frame index out of range for {len(sequence.frames)} frames")
    poses = _check_poses(poses_world_cam, len(frames))
    voxel_size = _check_positive("voxel_size", voxel_size)
    sdf_trunc = _check_positive("sdf_trunc", sdf_trunc)
    depth_trunc = _check_positive("depth_trunc", depth_trunc)
    if sdf_trunc <= voxel_size:
        raise ValueError(f"sdf_trunc ({sdf_trunc}) must exceed voxel_size ({voxel_size})")
    if sdf_trunc > limits.MAX_TRUNC_VOXELS * voxel_size:
        raise ValueError(
            f"sdf_trunc ({sdf_trunc}) must be at most {limits.MAX_TRUNC_VOXELS:g} voxels "
            f"({limits.MAX_TRUNC_VOXELS * voxel_size:g} m): the memory grows with it"
        )
    if int(min_observations) < 1:
        raise ValueError(f"min_observations must be >= 1, got {min_observations}")

    o3d = require_open3d()
    o3c = o3d.core
    cpu = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"),
        attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1), (1)),
        voxel_size=voxel_size,
        block_resolution=_BLOCK_RESOLUTION,
        block_count=_INITIAL_BLOCKS,
        device=cpu,
    )
    # the voxel block grid reads the pixel that contains a voxel's projection, which is the
    # pixel-centre convention of byoc_cli.io.rgbd.backproject: K is used as it is (measured
    # on exact synthetic renders: a -0.5 shift of c costs 1 cm at 50 px focal length)
    intrinsic = o3c.Tensor(np.asarray(sequence.K, dtype=np.float64), o3c.float64)
    depth_scale = float(sequence.depth_scale)
    multiplier = sdf_trunc / voxel_size
    integrated = 0
    for k, pose in zip(frames, poses, strict=True):
        raw = _raw_depth(sequence.read_depth(k), depth_scale)
        if not np.any((raw > 0) & (raw <= depth_trunc * depth_scale)):
            continue  # nothing to integrate (open3d would raise "no block is touched")
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(raw)))
        # extrinsic = T_cam_ref, the inverse of the frame's pose in the first frame's frame
        extrinsic = o3c.Tensor(relative_pose(pose, poses[0]), o3c.float64)
        blocks = grid.compute_unique_block_coordinates(
            depth, intrinsic, extrinsic, depth_scale, depth_trunc, trunc_voxel_multiplier=multiplier
        )
        grid.integrate(
            blocks, depth, intrinsic, extrinsic, depth_scale, depth_trunc,
            trunc_voxel_multiplier=multiplier,
        )  # fmt: skip
        integrated += 1
    if integrated == 0:
        return np.zeros((0, 3), dtype=np.float32)
    try:
        # the weight counts observations and the threshold is strict: n - 0.5 keeps n or more
        cloud = grid.extract_point_cloud(weight_threshold=int(min_observations) - 0.5)
    except RuntimeError as exc:  # open3d 0.20 raises instead of returning an empty cloud
        if "has shape {0}" not in str(exc):
            raise
        return np.zeros((0, 3), dtype=np.float32)
    if "positions" not in cloud.point:
        return np.zeros((0, 3), dtype=np.float32)
    points = np.asarray(cloud.point.positions.numpy(), dtype=np.float32).reshape(-1, 3)
    # open3d's hash map returns the points in an order that changes from run to run; sorted,
    # a fragment is the same file every time (and so is every registration that samples it)
    return np.ascontiguousarray(points[np.lexsort(points.T[::-1])])


# ================================================================== ground truth
