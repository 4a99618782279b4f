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

gt.log keeps the pairs whose overlap lies in the band ``(min_overlap, max_overlap]``: 3DMatch's
pairs are ``(0.3, 1]``, 3DLoMatch's ``(0.1, 0.3]`` (Huang et al., Predator, CVPR 2021).

Depth pixels are back-projected through their centres (``u + 0.5``), as everywhere in this
project (:func:`byoc_cli.io.rgbd.backproject`).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from byoc_cli.errors import DatasetError, InputError
from byoc_cli.io.atomic import atomic_write_text
from byoc_cli.io.folders import StagingFolder, remove_stale_staging
from byoc_cli.io.pointcloud import write_ply
from byoc_cli.io.rgbd import RGBDSequence
from byoc_cli.io.threedmatch import EVALUATION_SUFFIX
from byoc_cli.io.threedmatch_write import write_gt_info, write_gt_log, write_gt_overlap
from byoc_cli.pipeline.fragment_metrics import (
    INFO_MAX_CORRESPONDENCES,
    INFO_RADIUS,
    INFO_VOXEL,
    OVERLAP_RADIUS,
    OVERLAP_VOXEL,
    _information_of_clouds,
    _o3d_cloud,
    _overlap_of_clouds,
    fragment_overlap,
    information_matrix,
)
from byoc_cli.pipeline.fusion import (
    DEFAULT_DEPTH_TRUNC,
    DEFAULT_FRAMES_PER_FRAGMENT,
    DEFAULT_MIN_OBSERVATIONS,
    DEFAULT_SDF_TRUNC,
    DEFAULT_TSDF_VOXEL,
    fragment_windows,
    fuse_fragment,
    relative_pose,
)

__all__ = [
    "DEFAULT_DEPTH_TRUNC",
    "DEFAULT_FRAMES_PER_FRAGMENT",
    "DEFAULT_MAX_OVERLAP",
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

#: Pairs with an overlap above this go to gt.log (3DMatch: 30 %; 3DLoMatch: 10 %).
DEFAULT_MIN_OVERLAP = 0.3
#: Pairs with an overlap up to this go to gt.log (1: no upper bound; 3DLoMatch: 30 %).
DEFAULT_MAX_OVERLAP = 1.0
_SCENE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@+-]*$")


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


def _staging_dir(out_dir: Path) -> StagingFolder:
    """A new hidden folder beside ``out_dir``, renamed to it when everything is written;
    the ones that killed runs left beside it are removed first."""
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(out_dir, f"cannot create the folder ({exc.strerror or exc})") from exc
    remove_stale_staging(out_dir)
    return StagingFolder(out_dir)


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


def _candidate_pairs(
    fragments: list[_Fragment], min_overlap: float, max_overlap: float
) -> list[PairInfo]:
    """The pairs ``i < j`` whose overlap lies in ``(min_overlap, max_overlap]``, in order."""
    pairs = []
    for a, frag_i in enumerate(fragments):
        for frag_j in fragments[a + 1 :]:
            T = relative_pose(frag_i.info.pose, frag_j.info.pose)
            overlap = _overlap_of_clouds(
                frag_i.overlap_cloud, frag_j.overlap_cloud, T, OVERLAP_RADIUS
            )
            if not min_overlap < overlap <= max_overlap:
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


@dataclass(frozen=True)
class FragmentSettings:
    """How :func:`make_fragment_benchmark` cuts, fuses and pairs the fragments.

    Attributes:
        frames_per_fragment, stride: see :func:`fragment_windows`.
        voxel_size, sdf_trunc, depth_trunc, min_observations: see :func:`fuse_fragment`.
        min_overlap, max_overlap: pairs with ``min_overlap < overlap <= max_overlap``
            (:func:`fragment_overlap`) are kept; ``(0.1, 0.3]`` is a 3DLoMatch-style band.
    """

    frames_per_fragment: int = DEFAULT_FRAMES_PER_FRAGMENT
    stride: int | None = None
    voxel_size: float = DEFAULT_TSDF_VOXEL
    sdf_trunc: float = DEFAULT_SDF_TRUNC
    depth_trunc: float = DEFAULT_DEPTH_TRUNC
    min_observations: int = DEFAULT_MIN_OBSERVATIONS
    min_overlap: float = DEFAULT_MIN_OVERLAP
    max_overlap: float = DEFAULT_MAX_OVERLAP


def make_fragment_benchmark(
    sequence: RGBDSequence,
    out_dir: str | os.PathLike[str],
    *,
    scene: str,
    on_fragment: Callable[[FragmentInfo, int], None] | None = None,
    **settings: Any,
) -> FragmentBenchmark:
    """Fuse a posed sequence into fragments and write a 3DMatch-layout benchmark.

    Writes ``out_dir/<scene>/cloud_bin_K.ply`` (binary PLY, x y z float32, each fragment in
    its first frame's camera frame), ``out_dir/<scene>-evaluation/gt.log``, ``gt.info`` and
    ``gt_overlap.log`` (pairs ``i < j`` whose overlap lies in ``(min_overlap, max_overlap]``),
    and
    ``out_dir/make-fragments.json`` (settings, frames and pose of every fragment). Everything
    is written into a hidden folder beside ``out_dir`` that is renamed to ``out_dir`` at the
    end, so an error leaves nothing behind.

    Args:
        sequence: a sequence whose frames all have poses (``T_world_cam``).
        out_dir: the benchmark root; must not exist or be an empty folder.
        scene: the scene name.
        on_fragment: called with each fused fragment and the number of fragments.
        settings: the fields of :class:`FragmentSettings` (``frames_per_fragment``,
            ``stride``, ``voxel_size``, ``sdf_trunc``, ``depth_trunc``,
            ``min_observations``, ``min_overlap``, ``max_overlap``).

    Returns:
        :class:`FragmentBenchmark`.

    Raises:
        InputError: ``out_dir`` exists and is not an empty folder, or cannot be written.
        DatasetError: a frame has no pose, the sequence is shorter than one fragment, or a
            fragment has no point.
        FrameError: a depth image cannot be read.
        ValueError: bad settings or scene name.
        TypeError: an unknown setting.
    """
    fs = FragmentSettings(**settings)
    frames_per_fragment, stride, min_overlap = fs.frames_per_fragment, fs.stride, fs.min_overlap
    max_overlap = fs.max_overlap
    voxel_size, sdf_trunc, depth_trunc = fs.voxel_size, fs.sdf_trunc, fs.depth_trunc
    min_observations = fs.min_observations
    out_dir = Path(out_dir)
    scene = _check_scene(scene)
    if not 0.0 <= float(min_overlap) < 1.0:
        raise ValueError(f"min_overlap must lie in [0, 1), got {min_overlap}")
    if not float(min_overlap) < float(max_overlap) <= 1.0:
        raise ValueError(
            f"max_overlap must lie in (min_overlap, 1] = ({min_overlap}, 1], got {max_overlap}"
        )
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
        "max_overlap": max_overlap,
        "overlap": {"voxel": OVERLAP_VOXEL, "radius": OVERLAP_RADIUS, "direction": "min"},
        "info": {"voxel": INFO_VOXEL, "radius": INFO_RADIUS, "max": INFO_MAX_CORRESPONDENCES},
    }  # fmt: skip

    folder = _staging_dir(out_dir)
    staging = folder.path
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
        pairs = _candidate_pairs(fragments, float(min_overlap), float(max_overlap))
        if not pairs:
            warnings.warn(
                f"no pair of the {len(fragments)} fragments overlaps by more than "
                f"{min_overlap:.0%}"
                + (f" and at most {max_overlap:.0%}" if max_overlap < 1 else "")
                + ": gt.log is empty",
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
    finally:
        folder.release()
    return result
