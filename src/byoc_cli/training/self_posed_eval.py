"""Validation and export of the ``self-posed`` variant.

Validation: feature-match recall (FCGF's protocol) of posed frame pairs ``val_spacing``
frames apart. Export: the encoder as a weights file, from a live run or from any checkpoint.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from byoc_cli.training.config import TrainConfig
from byoc_cli.training.plot import read_metrics
from byoc_cli.training.pseudo_poses import frame_points

#: feature-match recall of the validation (FCGF's protocol)
FMR_INLIER_DISTANCE = 0.10
FMR_INLIER_RATIO = 0.05
FMR_SAMPLES = 5000


@torch.no_grad()
def feature_match_validation(
    encoder: torch.nn.Module, val_pairs: list[tuple[Any, int, int]], voxel_size: float, seed: int
) -> dict[str, float]:
    """FMR and mean inlier ratio (nearest neighbour in feature space) of posed frame pairs."""
    from byoc_cli.geometry.voxel import voxelize
    from byoc_cli.models.encoder import encode_voxels

    was_training = encoder.training
    encoder.eval()
    generator = torch.Generator().manual_seed(seed)
    ratios = []
    cache: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor]] = {}

    def featured(sequence: Any, key: tuple[int, int], frame: int):
        if key not in cache:
            points = torch.from_numpy(frame_points(sequence, frame))
            grid = voxelize(points, voxel_size)
            cache[key] = (points[grid.point_index], encode_voxels(encoder, grid.coords))
        return cache[key]

    for s, (sequence, i, j) in enumerate(val_pairs):
        del s
        p_i, f_i = featured(sequence, (id(sequence), i), i)
        p_j, f_j = featured(sequence, (id(sequence), j), j)
        T_i_j = torch.from_numpy(np.linalg.inv(sequence.pose(i)) @ sequence.pose(j)).float()
        pick = torch.randperm(len(p_j), generator=generator)[:FMR_SAMPLES]
        nn_idx = torch.cdist(f_j[pick], f_i).argmin(dim=1)
        moved = p_j[pick] @ T_i_j[:3, :3].T + T_i_j[:3, 3]
        inlier = (moved - p_i[nn_idx]).norm(dim=1) < FMR_INLIER_DISTANCE
        ratios.append(float(inlier.float().mean()))
    encoder.train(was_training)
    ratios_arr = np.asarray(ratios)
    return {
        "fmr": float(np.mean(ratios_arr > FMR_INLIER_RATIO)) if len(ratios) else float("nan"),
        "inlier_ratio": float(ratios_arr.mean()) if len(ratios) else float("nan"),
        "num_pairs": float(len(ratios)),
    }


def validation_pairs(config: TrainConfig) -> list[tuple[Any, int, int]]:
    """Consecutive frames ``val_spacing`` apart of every posed validation sequence."""
    from byoc_cli.io.rgbd import discover_sequences

    pairs = []
    for root in config.val_dir:
        for sequence in discover_sequences(root, require_poses=True):
            frames = list(range(0, len(sequence.frames), config.val_spacing))
            pairs += [(sequence, a, b) for a, b in itertools.pairwise(frames)]
    if config.val_max_pairs and len(pairs) > config.val_max_pairs:
        pick = np.linspace(0, len(pairs) - 1, config.val_max_pairs).round().astype(int)
        pairs = [pairs[k] for k in pick]
    return pairs


def export_encoder(
    encoder: torch.nn.Module,
    config: TrainConfig,
    path: Path,
    data: list[str],
    steps: int,
    metrics: dict[str, float],
    dtype: torch.dtype = torch.float32,
) -> str:
    """Write the encoder as a weights file (variant ``self-posed``); returns its SHA-256."""
    from byoc_cli.training.run_folder import write_encoder

    recipe = {
        k: config.to_dict()[k]
        for k in (
            "lr",
            "batch_size",
            "num_positives",
            "loss",
            "temperature",
            "pos_margin",
            "neg_margin",
            "aug_rotation_deg",
            "aug_scale",
            "aug_min_keep",
            "pair_gaps",
            "crop_radius",
            "aug_hole_prob",
            "aug_hole_min_keep",
            "round_steps",
            "round_gaps",
        )
    }
    recipe["rounds"] = config.round_of(max(steps - 1, 0))
    return write_encoder(encoder, config, path, data, steps, metrics, recipe=recipe, dtype=dtype)


def _run_data_names(run_dir: Path, config: TrainConfig) -> list[str]:
    """The training sequences a run folder's ``config.json`` names, else the folders of
    ``config.rgbd_dir`` (export reduces paths to names)."""
    try:
        names = json.loads((run_dir / "config.json").read_text(encoding="utf-8"))["data"]
    except (OSError, ValueError, KeyError, TypeError):
        names = None
    if isinstance(names, list) and names and all(isinstance(n, str) for n in names):
        return names
    return list(config.rgbd_dir)


def export_checkpoint(
    checkpoint: str | Path, path: str | Path, dtype: torch.dtype = torch.float32
) -> str:
    """Write the encoder of a ``self-posed`` checkpoint as a weights file; returns its SHA-256.

    Lets a running campaign be measured (or shipped) at any checkpoint without stopping it.
    """
    from byoc_cli.models.encoder import build_encoder
    from byoc_cli.training.checkpoint import load_checkpoint

    state = load_checkpoint(checkpoint)
    config = TrainConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in state["config"].items()}
    )
    encoder = build_encoder(config.arch)
    encoder.load_state_dict(state["model"])
    metrics: dict[str, float] = {}
    metrics_path = Path(checkpoint).parents[1] / "metrics.jsonl"
    if metrics_path.exists():
        records = read_metrics(metrics_path)
        vals = [r for r in records if r.get("kind") == "val" and r["step"] <= state["step"]]
        if vals:
            metrics = {
                f"val_{k}": v
                for k, v in vals[-1].items()
                if k not in ("kind", "step", "val_time_s")
            }
    data = _run_data_names(Path(checkpoint).parents[1], config)
    return export_encoder(
        encoder, config, Path(path), data, int(state["step"]), metrics, dtype=dtype
    )
