"""A 3DMatch-style fragment benchmark from a posed RGB-D sequence (``byoc make-fragments``).

The 3DMatch recipe (Zeng et al., CVPR 2017): every ``N`` consecutive depth frames (50 at
30 Hz) are fused into one fragment by TSDF fusion at 6 mm voxels, and the fragment's points are
expressed in the camera frame of its FIRST frame. Fusion uses Open3D's hashed, sparse voxel
block TSDF (``open3d.t.geometry.VoxelBlockGrid``, the volume of Open3D's reconstruction system;
the legacy ``ScalableTSDFVolume`` of open3d 0.20 integrates nothing here, measured); a voxel
on the zero crossing seen by at least ``min_observations`` frames gives one point.

Ground truth between fragments ``i < j`` (poses are camera-to-world ``T_world_cam`` of each
fragment's first frame):

* ``T_i_j = inv(pose_i) @ pose_j`` maps the points of ``j`` into the frame of ``i`` (the
  gt.log direction, ``T_tgt_src`` with target ``i``, source ``j``);
* overlap (:func:`fragment_overlap`): both fragments voxelised at 2.5 cm (Open3D voxel
  centroids), the share of one fragment's points with a point of the other within 3.75 cm
  (1.5 voxels) after ``T_i_j``; the MINIMUM of the two directions. On the real 3DMatch
  sample it keeps the three 3DMatch pairs (> 0.30) and rejects the five 3DLoMatch pairs;
* information matrix (:func:`information_matrix`): the official ``gt.info`` convention.

Depth pixels are back-projected through their centres (``u + 0.5``), as everywhere in this
project (:func:`byoc_cli.io.rgbd.backproject`).
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import shutil
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from byoc_cli.errors import DatasetError, InputError, ShapeError, require_open3d
from byoc_cli.io.atomic import atomic_write_text
from byoc_cli.io.pointcloud import write_ply
from byoc_cli.io.rgbd import RGBDSequence
from byoc_cli.io.threedmatch import EVALUATION_SUFFIX
from byoc_cli.io.threedmatch_write import write_gt_info, write_gt_log, write_gt_overlap

__all__ = [
    "DEFAULT_DEPTH_TRUNC",
    "DEFAULT_FRAMES_PER_FRAGMENT",
    "DEFAULT_MIN_OVERLAP",
    "DEFAULT_SDF_TRUNC",
    "DEFAULT_TSDF_VOXEL",
    "FragmentBenchmark",
    "FragmentInfo",
    "PairInfo",
    "fragment_overlap",
    "fragment_windows",
    "fuse_fragment",
    "information_matrix",
    "make_fragment_benchmark",
    "relative_pose",
]

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
#: Pairs with an overlap above this go to gt.log (3DMatch: 30 %).
DEFAULT_MIN_OVERLAP = 0.3
#: Overlap: voxel of the clouds compared, and the neighbour radius (1.5 voxels), metres.
OVERLAP_VOXEL = 0.025
OVERLAP_RADIUS = 0.0375
#: Information matrix: both fragments voxelised at 1 cm; a correspondence is a source point
#: with a target point within 6 mm; at most 5000 correspondences (the official files' cap).
INFO_VOXEL = 0.01
INFO_RADIUS = 0.006
INFO_MAX_CORRESPONDENCES = 5000
#: Hash-table blocks of 16^3 voxels reserved at first (the table grows when needed).
_BLOCK_RESOLUTION = 16
_INITIAL_BLOCKS = 20_000
_UINT16_MAX = 65535
_SCENE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@+-]*$")
#: Open3D's information matrix orders (rotation, translation); gt.info (translation, rotation).
_O3D_TO_GT_INFO = [3, 4, 5, 0, 1, 2]


class FragmentInfo(NamedTuple):
    """One fragment of the benchmark.

    Attributes:
        index: ``K`` of ``cloud_bin_K.ply``.
        frames: positions in the sequence's frames that were fused, first one first.
        num_points: points written.
        pose: ``(4, 4)`` float64 ``T_world_cam`` of the first frame (the fragment's frame).
    """

    index: int
    frames: tuple[int, ...]
    num_points: int
    pose: np.ndarray


class PairInfo(NamedTuple):
    """One pair kept in gt.log.

    Attributes:
        i, j: target and source fragments (``i < j``).
        overlap: :func:`fragment_overlap` of the pair.
        T_tgt_src: ``(4, 4)`` float64 ``T_i_j``.
        info: ``(6, 6)`` float64 information matrix.
    """

    i: int
    j: int
    overlap: float
    T_tgt_src: np.ndarray
    info: np.ndarray


class FragmentBenchmark(NamedTuple):
    """What :func:`make_fragment_benchmark` wrote.

    Attributes:
        out_dir: the benchmark root.
        scene: the scene name (``out_dir/<scene>/cloud_bin_K.ply``).
        fragments: every fragment, in order.
        pairs: the pairs of gt.log, in file order.
        num_candidate_pairs: pairs whose overlap was measured (all ``i < j``).
    """

    out_dir: Path
    scene: str
    fragments: list[FragmentInfo]
    pairs: list[PairInfo]
    num_candidate_pairs: int


# ================================================================== small helpers


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
        ``(N, 3)`` float32 points in metres, in the first frame's camera frame (N may be 0).

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
    return np.ascontiguousarray(cloud.point.positions.numpy(), dtype=np.float32).reshape(-1, 3)


# ================================================================== ground truth


def _o3d_cloud(points: np.ndarray, voxel: float | None = None):
    o3d = require_open3d()
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points must be (N, 3), got {points.shape}")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return cloud.voxel_down_sample(voxel) if voxel is not None else cloud


def _transformed(cloud, T: np.ndarray):
    moved = type(cloud)(cloud)
    moved.transform(np.asarray(T, dtype=np.float64))
    return moved


def _share_within(query, reference, radius: float) -> float:
    """Share of ``query``'s points with a ``reference`` point within ``radius``."""
    if len(query.points) == 0:
        return 0.0
    if len(reference.points) == 0:
        return 0.0
    distances = np.asarray(query.compute_point_cloud_distance(reference))
    return float(np.mean(distances < radius))


def _overlap_of_clouds(tgt, src, T_tgt_src: np.ndarray, radius: float) -> float:
    src_in_tgt = _transformed(src, T_tgt_src)
    return min(_share_within(src_in_tgt, tgt, radius), _share_within(tgt, src_in_tgt, radius))


def fragment_overlap(
    points_tgt: np.ndarray,
    points_src: np.ndarray,
    T_tgt_src: np.ndarray,
    *,
    voxel_size: float = OVERLAP_VOXEL,
    radius: float = OVERLAP_RADIUS,
) -> float:
    """Overlap of two fragments under their ground truth (symmetric, conservative).

    Objective: both clouds voxelised at ``voxel_size`` (Open3D voxel centroids), the source
    moved by ``T_tgt_src``; the share of source points with a target point within ``radius``
    and the share of target points with a source point within ``radius``; the minimum.

    Args:
        points_tgt: ``(N, 3)`` fragment ``i``.
        points_src: ``(M, 3)`` fragment ``j``.
        T_tgt_src: ``(4, 4)`` maps ``j`` into ``i``.
        voxel_size, radius: metres.

    Returns:
        Overlap in [0, 1] (0 when a cloud is empty).

    Raises:
        ShapeError: wrong shapes.
    """
    T = np.asarray(T_tgt_src, dtype=np.float64)
    if T.shape != (4, 4):
        raise ShapeError(f"T_tgt_src must be (4, 4), got {T.shape}")
    voxel_size = _check_positive("voxel_size", voxel_size)
    radius = _check_positive("radius", radius)
    tgt, src = _o3d_cloud(points_tgt, voxel_size), _o3d_cloud(points_src, voxel_size)
    return _overlap_of_clouds(tgt, src, T, radius)


def _information_of_clouds(
    tgt, src, T_tgt_src: np.ndarray, radius: float, max_correspondences: int
) -> np.ndarray:
    o3d = require_open3d()
    if len(tgt.points) == 0 or len(src.points) == 0:
        return np.zeros((6, 6))
    info = np.asarray(
        o3d.pipelines.registration.get_information_matrix_from_point_clouds(
            src, tgt, radius, np.asarray(T_tgt_src, dtype=np.float64)
        ),
        dtype=np.float64,
    )[np.ix_(_O3D_TO_GT_INFO, _O3D_TO_GT_INFO)]
    count = info[0, 0]
    if count > max_correspondences:
        info *= max_correspondences / count
    return info


def information_matrix(
    points_tgt: np.ndarray,
    points_src: np.ndarray,
    T_tgt_src: np.ndarray,
    *,
    voxel_size: float = INFO_VOXEL,
    radius: float = INFO_RADIUS,
    max_correspondences: int = INFO_MAX_CORRESPONDENCES,
) -> np.ndarray:
    """The 6x6 ``gt.info`` information matrix of a pair, in the official convention.

    Objective: both clouds voxelised at ``voxel_size``; the correspondences are the source
    points (moved by ``T_tgt_src``) with a target point within ``radius``; with ``p = (x, y,
    z)`` the TARGET point of each, ``A = [I | -[p]x]`` (``[p]x`` the cross-product matrix),
    ``info = sum A^T A`` (Open3D's ``get_information_matrix_from_point_clouds``, reordered
    translation first, as in gt.info), scaled so that ``info[0, 0] = min(count,
    max_correspondences)`` (the official files stop at 5000). Its top-left block is
    ``N * I``; :func:`byoc_cli.evaluation.metrics.registration_rmse` divides by ``info[0, 0]``.
    On the real 3DMatch sample (redkitchen pairs 0-4 and 4-7) it matches the official gt.info
    within 1 % of the largest entry.

    Args:
        points_tgt: ``(N, 3)`` fragment ``i``.
        points_src: ``(M, 3)`` fragment ``j``.
        T_tgt_src: ``(4, 4)`` maps ``j`` into ``i``.
        voxel_size, radius: metres.
        max_correspondences: cap of ``info[0, 0]``.

    Returns:
        ``(6, 6)`` float64, symmetric (all zeros when no correspondence is found).

    Raises:
        ShapeError: wrong shapes.
    """
    T = np.asarray(T_tgt_src, dtype=np.float64)
    if T.shape != (4, 4):
        raise ShapeError(f"T_tgt_src must be (4, 4), got {T.shape}")
    voxel_size = _check_positive("voxel_size", voxel_size)
    radius = _check_positive("radius", radius)
    tgt, src = _o3d_cloud(points_tgt, voxel_size), _o3d_cloud(points_src, voxel_size)
    return _information_of_clouds(tgt, src, T, radius, int(max_correspondences))


# ================================================================== the benchmark


def _check_scene(scene: str) -> str:
    if not _SCENE_NAME.match(scene) or scene.endswith(EVALUATION_SUFFIX):
        raise ValueError(
            f"scene name {scene!r} must be letters, digits and ._@+- (no path separator, not "
            f"ending in {EVALUATION_SUFFIX})"
        )
    return scene


def _check_out_dir(out_dir: Path) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(out_dir, "exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        raise InputError(out_dir, "folder exists and is not empty (choose a new --out folder)")


def _staging_dir(out_dir: Path) -> Path:
    """A new hidden folder beside ``out_dir``, renamed to it when everything is written."""
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        staging = out_dir.parent / f".{out_dir.name}.{secrets.token_hex(4)}.tmp"
        staging.mkdir()
    except OSError as exc:
        raise InputError(out_dir, f"cannot create the folder ({exc.strerror or exc})") from exc
    return staging


def _publish(staging: Path, out_dir: Path) -> None:
    try:
        if out_dir.is_dir():
            out_dir.rmdir()  # empty (checked); os.rename cannot replace a folder on Windows
        os.rename(staging, out_dir)
    except OSError as exc:
        raise InputError(out_dir, f"cannot create the folder ({exc.strerror or exc})") from exc


class _Fragment(NamedTuple):
    info: FragmentInfo
    overlap_cloud: Any
    info_cloud: Any


def _candidate_pairs(fragments: list[_Fragment], min_overlap: float) -> list[PairInfo]:
    pairs = []
    for a, frag_i in enumerate(fragments):
        for frag_j in fragments[a + 1 :]:
            T = relative_pose(frag_i.info.pose, frag_j.info.pose)
            overlap = _overlap_of_clouds(
                frag_i.overlap_cloud, frag_j.overlap_cloud, T, OVERLAP_RADIUS
            )
            if overlap <= min_overlap:
                continue
            info = _information_of_clouds(
                frag_i.info_cloud, frag_j.info_cloud, T, INFO_RADIUS, INFO_MAX_CORRESPONDENCES
            )
            pairs.append(PairInfo(frag_i.info.index, frag_j.info.index, overlap, T, info))
    return pairs


def _manifest(
    sequence: RGBDSequence, scene: str, settings: dict[str, Any], result: FragmentBenchmark
) -> str:
    from byoc_cli import __version__

    frames = sequence.frames
    return json.dumps(
        {
            "byoc_version": __version__,
            "sequence": str(sequence.root),
            "layout": sequence.layout,
            "scene": scene,
            "settings": settings,
            "fragments": [
                {
                    "index": f.index,
                    "frames": [f.frames[0], f.frames[-1]],
                    "depth_files": [str(frames[f.frames[0]].depth_path.name),
                                    str(frames[f.frames[-1]].depth_path.name)],
                    "num_points": f.num_points,
                    "T_world_cam": f.pose.tolist(),
                }
                for f in result.fragments
            ],
            "pairs": [{"i": p.i, "j": p.j, "overlap": round(p.overlap, 4)} for p in result.pairs],
        },
        indent=1,
    ) + "\n"  # fmt: skip


def make_fragment_benchmark(
    sequence: RGBDSequence,
    out_dir: str | os.PathLike[str],
    *,
    scene: str,
    frames_per_fragment: int = DEFAULT_FRAMES_PER_FRAGMENT,
    stride: int | None = None,
    voxel_size: float = DEFAULT_TSDF_VOXEL,
    sdf_trunc: float = DEFAULT_SDF_TRUNC,
    depth_trunc: float = DEFAULT_DEPTH_TRUNC,
    min_observations: int = DEFAULT_MIN_OBSERVATIONS,
    min_overlap: float = DEFAULT_MIN_OVERLAP,
    on_fragment: Callable[[FragmentInfo, int], None] | None = None,
) -> FragmentBenchmark:
    """Fuse a posed sequence into fragments and write a 3DMatch-layout benchmark.

    Writes ``out_dir/<scene>/cloud_bin_K.ply`` (binary PLY, x y z float32, each fragment in
    its first frame's camera frame), ``out_dir/<scene>-evaluation/gt.log``, ``gt.info`` and
    ``gt_overlap.log`` (pairs ``i < j`` with overlap above ``min_overlap``), and
    ``out_dir/make-fragments.json`` (settings, frames and pose of every fragment). Everything
    is written into a hidden folder beside ``out_dir`` that is renamed to ``out_dir`` at the
    end, so an error leaves nothing behind.

    Args:
        sequence: a sequence whose frames all have poses (``T_world_cam``).
        out_dir: the benchmark root; must not exist or be an empty folder.
        scene: the scene name.
        frames_per_fragment, stride: see :func:`fragment_windows`.
        voxel_size, sdf_trunc, depth_trunc, min_observations: see :func:`fuse_fragment`.
        min_overlap: pairs with a larger :func:`fragment_overlap` are kept.
        on_fragment: called with each fused fragment and the number of fragments.

    Returns:
        :class:`FragmentBenchmark`.

    Raises:
        InputError: ``out_dir`` exists and is not an empty folder, or cannot be written.
        DatasetError: a frame has no pose, the sequence is shorter than one fragment, or a
            fragment has no point.
        FrameError: a depth image cannot be read.
        ValueError: bad settings or scene name.
    """
    out_dir = Path(out_dir)
    scene = _check_scene(scene)
    if not 0.0 <= float(min_overlap) < 1.0:
        raise ValueError(f"min_overlap must lie in [0, 1), got {min_overlap}")
    windows = fragment_windows(len(sequence.frames), frames_per_fragment, stride)
    if not windows:
        raise DatasetError(
            sequence.root,
            f"{len(sequence.frames)} frames, fewer than one fragment's {frames_per_fragment}",
        )
    missing = [k for k, f in enumerate(sequence.frames) if f.pose is None]
    if missing:
        raise DatasetError(
            sequence.root, f"{len(missing)} frames have no pose (first: {missing[0]})"
        )
    _check_out_dir(out_dir)
    settings = {
        "frames_per_fragment": int(frames_per_fragment),
        "stride": int(stride if stride is not None else frames_per_fragment),
        "tsdf_voxel": voxel_size, "sdf_trunc": sdf_trunc, "depth_trunc": depth_trunc,
        "min_observations": min_observations, "min_overlap": min_overlap,
        "overlap": {"voxel": OVERLAP_VOXEL, "radius": OVERLAP_RADIUS, "direction": "min"},
        "info": {"voxel": INFO_VOXEL, "radius": INFO_RADIUS, "max": INFO_MAX_CORRESPONDENCES},
    }  # fmt: skip

    staging = _staging_dir(out_dir)
    try:
        (staging / scene).mkdir()
        (staging / f"{scene}{EVALUATION_SUFFIX}").mkdir()
        fragments = []
        for index, window in enumerate(windows):
            poses = np.stack([sequence.frames[k].pose for k in window])
            points = fuse_fragment(
                sequence, window, poses, voxel_size=voxel_size, sdf_trunc=sdf_trunc,
                depth_trunc=depth_trunc, min_observations=min_observations,
            )  # fmt: skip
            if len(points) == 0:
                raise DatasetError(
                    sequence.frames[window[0]].depth_path,
                    f"fragment {index} (frames {window[0]}-{window[-1]}) has no point "
                    "(no valid depth below the depth truncation?)",
                )
            write_ply(staging / scene / f"cloud_bin_{index}.ply", points)
            info = FragmentInfo(index, tuple(window), len(points), poses[0].copy())
            fragments.append(
                _Fragment(info, _o3d_cloud(points, OVERLAP_VOXEL), _o3d_cloud(points, INFO_VOXEL))
            )
            if on_fragment is not None:
                on_fragment(info, len(windows))
        pairs = _candidate_pairs(fragments, float(min_overlap))
        if not pairs:
            warnings.warn(
                f"no pair of the {len(fragments)} fragments overlaps by more than "
                f"{min_overlap:.0%}: gt.log is empty",
                stacklevel=2,
            )
        n = len(fragments)
        ij = [(p.i, p.j) for p in pairs]
        gt = staging / f"{scene}{EVALUATION_SUFFIX}"
        write_gt_log(gt / "gt.log", ij, [p.T_tgt_src for p in pairs], n)
        write_gt_info(gt / "gt.info", ij, [p.info for p in pairs], n)
        write_gt_overlap(gt / "gt_overlap.log", ij, [p.overlap for p in pairs])
        result = FragmentBenchmark(
            out_dir, scene, [f.info for f in fragments], pairs, n * (n - 1) // 2
        )
        atomic_write_text(
            staging / "make-fragments.json", _manifest(sequence, scene, settings, result)
        )
        _publish(staging, out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return result
