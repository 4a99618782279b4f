"""Training and validation pairs from RGB-D video (the paper's section 4, Datasets;
docs/training.md).

A pair ``(i, j)`` of one sequence (``j = i + spacing``) gives two views. View 0 is frame
``i`` (the *target*), view 1 is frame ``j`` (the *source*): registration estimates
``T_0_1 = T_tgt_src``, which maps view-1 points into view 0's camera frame. Its ground
truth, when the sequence has camera-to-world poses ``T_world_cam``, is
:func:`relative_pose` ``= inv(T_world_cam_i) @ T_world_cam_j``.

Each sample is preprocessed in the data-loader workers: 128x128 crop and resize with the
intrinsics adjusted, pixel-centre back-projection, and voxelisation at the geometric voxel
size (first point per voxel), so that both branches index the same kept points.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
from torch.utils.data import Dataset, DistributedSampler

from byoc_cli.geometry import voxelize
from byoc_cli.geometry.transforms import invert_transform


class View(NamedTuple):
    """One preprocessed frame.

    Attributes:
        points: ``(N, 3)`` float32 back-projected points, camera frame, metres.
        point_index: ``(M,)`` int64 first point per voxel (indices into ``points``).
        coords: ``(M, 3)`` int64 voxel coordinates of the kept points.
        color: ``(3, S, S)`` float32 in [-1, 1], or None for depth-only variants.
        K: ``(3, 3)`` float32 intrinsics of the ``S x S`` image.
    """

    points: torch.Tensor
    point_index: torch.Tensor
    coords: torch.Tensor
    color: torch.Tensor | None
    K: torch.Tensor


class PairSample(NamedTuple):
    """Two views of one sequence.

    Attributes:
        view0: frame ``i`` (target).
        view1: frame ``j`` (source).
        T_gt: ``(4, 4)`` float64 ``T_0_1`` (maps view-1 points into view 0) or None.
        sequence: index of the sequence in the dataset.
        frames: ``(i, j)``.
    """

    view0: View
    view1: View
    T_gt: torch.Tensor | None
    sequence: int
    frames: tuple[int, int]


def relative_pose(T_world_cam_i: Any, T_world_cam_j: Any) -> torch.Tensor:
    """Ground truth of a pair: ``T_i_j = inv(T_world_cam_i) @ T_world_cam_j``.

    Args:
        T_world_cam_i, T_world_cam_j: ``(4, 4)`` camera-to-world poses of frames i and j.

    Returns:
        ``(4, 4)`` float64 transform mapping frame-j camera points into frame i's camera.
    """
    Ti = torch.as_tensor(np.asarray(T_world_cam_i), dtype=torch.float64)
    Tj = torch.as_tensor(np.asarray(T_world_cam_j), dtype=torch.float64)
    return invert_transform(Ti) @ Tj


def sequence_name(sequence: Any, fallback: str) -> str:
    """A readable name for a sequence (its ``name``, else its root folder, else ``fallback``)."""
    for attr in ("name", "root", "path"):
        value = getattr(sequence, attr, None)
        if value:
            return str(value)
    return fallback


def _as_tensor(x: Any, dtype: torch.dtype) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(dtype)
    return torch.as_tensor(np.ascontiguousarray(x)).to(dtype)


def _pairs(num_frames: int, spacing: int, mode: str) -> list[tuple[int, int]]:
    from byoc_cli.io.rgbd import make_pairs

    out = []
    for pair in make_pairs(num_frames, spacing=spacing, mode=mode):
        i, j = (int(v) for v in pair)
        out.append((i, j))
    return out


class PairDataset(Dataset):
    """Pairs of frames ``view_spacing`` apart from one or more RGB-D sequences.

    Args:
        sequences: :class:`byoc_cli.io.rgbd.RGBDSequence` objects.
        spacing: frames between the two views.
        mode: ``"train"`` (every start frame) or ``"val"`` (every ``spacing``-th frame,
            consecutive ones paired).
        image_size: side of the square crop.
        voxel_size: voxel size for the kept points.
        use_color: read and preprocess colour (visual variants).
        with_poses: attach the ground-truth relative pose (validation).
    """

    def __init__(
        self,
        sequences: Sequence[Any],
        spacing: int,
        mode: str = "train",
        image_size: int = 128,
        voxel_size: float = 0.025,
        use_color: bool = False,
        with_poses: bool = False,
    ) -> None:
        self.sequences = list(sequences)
        self.spacing = int(spacing)
        self.mode = mode
        self.image_size = int(image_size)
        self.voxel_size = float(voxel_size)
        self.use_color = bool(use_color)
        self.with_poses = bool(with_poses)
        self.pairs: list[tuple[int, int, int]] = []
        for s, seq in enumerate(self.sequences):
            for i, j in _pairs(len(seq.frames), self.spacing, mode):
                self.pairs.append((s, i, j))

    def __len__(self) -> int:
        return len(self.pairs)

    def subset(self, max_pairs: int) -> PairDataset:
        """At most ``max_pairs`` pairs, evenly spread (deterministic); ``0`` keeps all."""
        if max_pairs <= 0 or max_pairs >= len(self.pairs):
            return self
        keep = np.linspace(0, len(self.pairs) - 1, max_pairs).round().astype(np.int64)
        out = PairDataset.__new__(PairDataset)
        out.__dict__.update(self.__dict__)
        out.pairs = [self.pairs[k] for k in sorted(set(keep.tolist()))]
        return out

    def load_view(self, sequence: Any, frame: int) -> View:
        """Read and preprocess one frame (crop/resize, back-project, voxelise)."""
        from byoc_cli.io.rgbd import backproject, preprocess_frame

        depth = sequence.read_depth(frame)
        color = sequence.read_color(frame) if self.use_color else None
        depth_s, color_s, K_s = preprocess_frame(depth, color, sequence.K, size=self.image_size)
        points, _pixel = backproject(depth_s, K_s)
        points = _as_tensor(points, torch.float32).reshape(-1, 3)
        grid = voxelize(points, self.voxel_size)
        color_t = None
        if color_s is not None:
            color_t = _as_tensor(color_s, torch.float32)
            if color_t.shape[0] != 3 and color_t.shape[-1] == 3:
                color_t = color_t.permute(2, 0, 1)
            color_t = color_t.contiguous()
        return View(points, grid.point_index, grid.coords, color_t, _as_tensor(K_s, torch.float32))

    def __getitem__(self, index: int) -> PairSample:
        s, i, j = self.pairs[index]
        seq = self.sequences[s]
        T_gt = None
        if self.with_poses:
            pose_i, pose_j = seq.pose(i), seq.pose(j)
            if pose_i is not None and pose_j is not None:
                T_gt = relative_pose(pose_i, pose_j)
        return PairSample(self.load_view(seq, i), self.load_view(seq, j), T_gt, s, (i, j))


def collate_pairs(samples: list[PairSample]) -> list[PairSample]:
    """Keep a batch as a list (clouds differ in size)."""
    return list(samples)


def worker_init(_worker_id: int) -> None:
    """One thread per data worker (the workers are processes already)."""
    torch.set_num_threads(1)


class ResumableSampler(DistributedSampler):
    """:class:`DistributedSampler` (shuffled by ``seed + epoch``, ``drop_last``) that can start
    part-way into an epoch, so that a resumed run sees exactly the remaining samples.

    Args:
        dataset: the dataset.
        num_replicas, rank: the process group (1, 0 without DDP).
        seed: data-order seed.
    """

    def __init__(
        self, dataset: Dataset, num_replicas: int = 1, rank: int = 0, seed: int = 0
    ) -> None:
        super().__init__(
            dataset, num_replicas=num_replicas, rank=rank, shuffle=True, seed=seed, drop_last=True
        )
        self.start_index = 0

    def set_position(self, epoch: int, start_index: int) -> None:
        """Iterate epoch ``epoch`` from its ``start_index``-th sample (of this rank)."""
        self.set_epoch(epoch)
        self.start_index = int(start_index)

    def __iter__(self) -> Iterator[int]:
        indices = list(super().__iter__())
        return iter(indices[self.start_index :])

    def __len__(self) -> int:
        return max(0, self.num_samples - self.start_index)
