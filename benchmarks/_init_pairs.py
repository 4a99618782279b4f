"""The pairs of benchmarks/init.py, made at run time from ../shared/data: posed RGB-D frames of
the TUM and RealSense sequences, their ground truth, and guesses perturbed from it.

A guess is the ground truth turned by a random rotation of a given angle about the source's
centroid (where the ground truth puts it) and moved by a random translation of a given length:
``T_init = P @ T_gt``; the correction a local registration must find is ``inv(P)``, whose
rotation is the angle and whose translation of the source's centroid is the length.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
RGBD = DATA / "rgbd"

#: the benchmark's pairs: (sequence, frames between the two views). TUM's Kinect runs at 30 Hz;
#: tum_fr1_desk_full keeps every second frame, so 25 of its frames are 50 of the camera's;
#: realsense_tabletop has 50 frames in all (first and last 67 deg apart): 15 apart.
BENCH_SETS = (("tum_fr1_desk_full", 25), ("tum_fr1_rpy", 50), ("realsense_tabletop", 15))
#: the calibration's pairs (``fit``): these sequences at several frame gaps
CALIBRATION_SETS = (
    ("tum_fr1_desk_full", 10),
    ("tum_fr1_desk_full", 25),
    ("tum_fr1_desk_full", 40),
    ("tum_fr1_rpy", 20),
    ("tum_fr1_rpy", 50),
    ("tum_fr3_cabinet", 1),
    ("tum_fr3_cabinet", 3),
    ("realsense_tabletop", 5),
    ("realsense_tabletop", 15),
    ("tum_fr1_desk", 4),
    ("tum_fr1_xyz", 4),
)


class Pair(NamedTuple):
    """One posed pair: its name, sequence, the loaders of its clouds and ``T_gt``."""

    name: str
    group: str
    load_source: object
    load_target: object
    T_gt: np.ndarray


def rgbd_pairs(sets=BENCH_SETS, limit: int | None = None) -> Iterator[Pair]:
    """The posed pairs of ``sets`` (every ``gap``-th frame, consecutive ones paired: the later
    frame is the source), at most ``limit`` in all."""
    from byoc_cli.evaluation.pairs import rgbd_pairs as make

    count = 0
    for sequence, gap in sets:
        found, _ = make([RGBD / sequence], spacing=gap)
        for p in found:
            if limit is not None and count >= limit:
                return
            count += 1
            yield Pair(f"{p.name}@{gap}", sequence, p.source.load, p.target.load, p.T_gt)


def rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """``(3, 3)`` rotation of ``degrees`` about ``axis (3,)`` (Rodrigues)."""
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = math.radians(degrees)
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def perturbed(
    T_gt: np.ndarray, centroid_src: np.ndarray, degrees: float, length: float, rng
) -> np.ndarray:
    """``T_gt (4, 4)`` turned by ``degrees`` about a random axis through the source's centroid
    ``centroid_src (3,)`` (source coordinates) and moved ``length`` in a random direction."""
    c = T_gt[:3, :3] @ centroid_src + T_gt[:3, 3]
    R = rotation(rng.normal(size=3), degrees)
    d = rng.normal(size=3)
    P = np.eye(4)
    P[:3, :3] = R
    P[:3, 3] = c - R @ c + d / np.linalg.norm(d) * length
    return P @ T_gt


def errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """Rotation (deg) and translation (units of T) of ``inv(T) @ T_gt``."""
    D = np.linalg.inv(T) @ T_gt
    cos = np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(D[:3, 3]))


def within(T: np.ndarray, T_gt: np.ndarray, degrees: float, metres: float) -> bool:
    rot, trans = errors(T, T_gt)
    return rot < degrees and trans < metres


#: a pair's truth is determined by the data when our refinement of the ground truth and
#: Open3D's agree within these (a quarter of 5 deg and 10 cm, as benchmarks/confidence.py)
CHECK_DEG, CHECK_M = 1.25, 0.025


#: a pair's clouds overlap at its truth when this share of the source (every 20th point) has a
#: target point within OVERLAP_M under it; below it the pose is not the data's to give (the
#: first fr1_rpy pairs 50 frames apart share nothing: 0 %)
MIN_OVERLAP, OVERLAP_M = 0.3, 0.05


def overlap(src: np.ndarray, tgt: np.ndarray, T: np.ndarray) -> float:
    """Share of every 20th point of ``src (N, 3)`` with a point of ``tgt (M, 3)`` within
    OVERLAP_M under ``T (4, 4)``."""
    from pykdtree.kdtree import KDTree

    points = src[::20].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    distance, _ = KDTree(tgt.astype(np.float64)).query(points, k=1)
    return float(np.mean(distance < OVERLAP_M))


def refined_truth(src: np.ndarray, tgt: np.ndarray, T_gt: np.ndarray, voxel: float):
    """``(T, determined)``: the ground truth refined on the data by the multiscale ICP, and
    whether Open3D's multiscale ICP from the ground truth ends within CHECK_DEG / CHECK_M
    of it (the data determine the pose)."""
    import torch

    from _confidence_truth import open3d_truth
    from byoc_cli.pipeline.refine import refine_multiscale

    ours = refine_multiscale(
        torch.from_numpy(src), torch.from_numpy(tgt), torch.from_numpy(T_gt), voxel
    ).T_tgt_src.numpy()
    theirs = open3d_truth(src, tgt, T_gt, 1.0)
    return ours, within(ours, theirs, CHECK_DEG, CHECK_M)
