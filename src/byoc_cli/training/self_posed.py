"""The ``self-posed`` training variant: metric learning on pairs the video poses itself.

No poses and no labels are read from the training data: each sequence's wide pairs and
their relative poses come from :mod:`byoc_cli.training.pseudo_poses` (the tool's own
registration, verified by fit and cycle consistency) and are cached in the run folder
(``pseudo_pairs/NN-<sequence>.json``). With ``round_steps``, training runs in rounds: at
the start of round ``r >= 2`` the sequences are posed again with the encoder as trained so
far as the global registration (:class:`~byoc_cli.training.pseudo_poses.LearnedStart`) and
the wider ``round_gaps`` added, cached in ``pseudo_pairs/round-r/``; each round's kept pairs
are logged (``metrics.jsonl``, records of kind ``round``). Each step draws ``batch_size``
pairs, makes two augmented views of each (:mod:`byoc_cli.training.self_posed_data`), encodes
all views in one batched sparse forward pass and applies the metric loss ``loss`` (symmetric
InfoNCE, or FCGF's hardest-contrastive) on up to ``num_positives`` dense correspondences per
pair. Validation (``val_dir``, posed sequences) measures the feature-match recall of frame
pairs ``val_spacing`` frames apart.

The loop (:mod:`byoc_cli.training.loop`) owns the run folder, the optimiser (Adam, fused),
checkpoints, records and export, as for the paper's variants; this module supplies the data
and the step (:class:`SelfPosedTask`).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from byoc_cli.errors import DatasetError, InputError
from byoc_cli.io.atomic import atomic_write_text
from byoc_cli.io.inputs import read_json_input
from byoc_cli.training.config import TrainConfig
from byoc_cli.training.metric_loss import hardest_contrastive, info_nce, sample_matches
from byoc_cli.training.pseudo_poses import (
    LearnedStart,
    PseudoPair,
    PseudoPoseConfig,
    config_dict,
    estimate_pairs,
    frame_points,
    pairs_from_json,
    pairs_to_json,
)
from byoc_cli.training.run_folder import load_initial_weights
from byoc_cli.training.self_posed_data import (
    AugmentConfig,
    CachedFrame,
    cache_frame,
    make_pair_views,
)
from byoc_cli.training.self_posed_eval import (
    export_encoder,
    feature_match_validation,
    validation_pairs,
)

log = logging.getLogger(__name__)

PAIRS_DIR = "pseudo_pairs"
#: the cache keeps the first point per voxel of this size relative to the encoder's voxel
CACHE_VOXEL_FACTOR = 0.5


def pseudo_config(config: TrainConfig, round_number: int = 1) -> PseudoPoseConfig:
    """The self-posing settings of a training configuration in round ``round_number``."""
    gaps = config.pair_gaps
    if round_number > 1:
        gaps += tuple(g for g in config.round_gaps if g not in config.pair_gaps)
    return PseudoPoseConfig(
        voxel_size=config.voxel_size,
        gaps=gaps,
        min_fitness=config.pair_min_fitness,
        seed=config.seed,
    )


def pairs_folder(run_dir: Path, round_number: int) -> Path:
    """Where a run caches the self-posed pairs of a round."""
    folder = run_dir / PAIRS_DIR
    return folder if round_number == 1 else folder / f"round-{round_number}"


def discover_training_sequences(config: TrainConfig) -> list[Any]:
    """The training sequences of ``config.rgbd_dir`` (depth only; poses are not used)."""
    from byoc_cli.io.rgbd import discover_sequences

    sequences = []
    for root in config.rgbd_dir:
        sequences += discover_sequences(
            root,
            intrinsics=config.intrinsics,
            depth_scale=config.depth_scale,
            read_poses=False,
        )
    if not sequences:
        raise DatasetError(", ".join(config.rgbd_dir), "holds no training sequence")
    return sequences


def load_or_estimate_pairs(
    config: TrainConfig,
    run_dir: Path,
    sequences: list[Any],
    progress=None,
    round_number: int = 1,
    encoder: torch.nn.Module | None = None,
) -> list[dict]:
    """Per sequence, the cached self-posed pairs record of a round (estimated on first use).

    Round 1 poses with the classical registration (or reuses ``config.pairs_from``); later
    rounds use ``encoder`` as the global registration.
    """
    folder = pairs_folder(run_dir, round_number)
    folder.mkdir(parents=True, exist_ok=True)
    settings = pseudo_config(config, round_number)
    learned = round_number > 1 and encoder is not None
    out = []
    for n, sequence in enumerate(sequences):
        path = folder / f"{n:02d}-{sequence.name}.json"
        reused = _reusable(config, sequence, settings) if round_number == 1 else None
        cached = read_json_input(path) if path.exists() else None
        if isinstance(cached, dict) and cached.get("config") == config_dict(settings):
            record = cached
        elif reused is not None:
            record = reused
            atomic_write_text(path, json.dumps(record, indent=1))
        else:
            t0 = time.perf_counter()
            start = LearnedStart(encoder, config.voxel_size, config.seed) if learned else None
            result = estimate_pairs(sequence, settings, progress, global_start=start)
            record = pairs_to_json(result, settings, sequence)
            record["round"] = round_number
            record["global_start"] = "learned" if learned else "fpfh"
            record["seconds"] = round(time.perf_counter() - t0, 1)
            atomic_write_text(path, json.dumps(record, indent=1))
        log.info(
            "round %d, %s: %d self-posed pairs (kept per gap %s)",
            round_number,
            path.name,
            len(record["pairs"]),
            record["kept"],
        )
        out.append(record)
    return out


def round_record(round_number: int, step: int, records: list[dict]) -> dict[str, Any]:
    """The ``metrics.jsonl`` record of what a round keeps (per sequence, per gap)."""
    return {
        "kind": "round",
        "round": round_number,
        "step": step,
        "pairs": sum(len(r["pairs"]) for r in records),
        "sequences": {
            r["name"]: {
                "pairs": len(r["pairs"]),
                "candidates": r["candidates"],
                "kept": r["kept"],
                "kept_learned_start": r["stats"].get("kept_learned_start", 0),
            }
            for r in records
        },
    }


def _reusable(config: TrainConfig, sequence: Any, settings: PseudoPoseConfig) -> dict | None:
    """The pairs of ``sequence`` in the run ``config.pairs_from``, if made with ``settings``."""
    if not config.pairs_from:
        return None
    wanted = config_dict(settings)
    for path in sorted((Path(config.pairs_from) / PAIRS_DIR).glob("*.json")):
        record = read_json_input(path)
        if not isinstance(record, dict) or not {"sequence", "config"} <= record.keys():
            raise InputError(path, "not a self-posed pairs record (pairs_from)")
        same_sequence = Path(str(record["sequence"])).resolve() == Path(sequence.root).resolve()
        if same_sequence and record["config"] == wanted:
            return record
    return None


def build_frame_cache(
    config: TrainConfig,
    sequences: list[Any],
    pairs: list[list[PseudoPair]],
    cache: dict[tuple[int, int], CachedFrame] | None = None,
    progress: Any = None,
) -> dict[tuple[int, int], CachedFrame]:
    """``(sequence, frame) -> CachedFrame`` for every frame of a kept pair (frames already in
    ``cache``, e.g. an earlier round's, are not read again); ``progress("cache", done,
    total)`` after each frame read."""
    cache = dict(cache or {})
    voxel = CACHE_VOXEL_FACTOR * config.voxel_size
    todo = [
        (s, f)
        for s, seq_pairs in enumerate(pairs)
        for f in sorted({p.i for p in seq_pairs} | {p.j for p in seq_pairs})
        if (s, f) not in cache
    ]
    for n, (s, f) in enumerate(todo):
        cache[(s, f)] = cache_frame(frame_points(sequences[s], f), voxel)
        if progress is not None:
            progress("cache", n + 1, len(todo))
    return cache


def encode_views(encoder: torch.nn.Module, coords: list[torch.Tensor]) -> list[torch.Tensor]:
    """Features of several views in one batched forward pass."""
    batch = torch.cat(
        [torch.cat([c.new_full((len(c), 1), b), c], dim=1) for b, c in enumerate(coords)]
    )
    feats = torch.ones(len(batch), encoder.config.in_channels)
    out = encoder(batch, feats)
    return list(torch.split(out, [len(c) for c in coords]))


def pair_loss(
    feats_i: torch.Tensor,
    feats_j: torch.Tensor,
    matches: torch.Tensor,
    points_i: torch.Tensor,
    config: TrainConfig,
) -> torch.Tensor:
    """The loss ``config.loss`` of one pair (shapes as in :mod:`byoc_cli.training.metric_loss`)."""
    if config.loss == "hardest-contrastive":
        return hardest_contrastive(
            feats_i,
            feats_j,
            matches,
            points_i,
            pos_margin=config.pos_margin,
            neg_margin=config.neg_margin,
        )
    return info_nce(feats_i, feats_j, matches, points_i, temperature=config.temperature)


def training_step(
    encoder: torch.nn.Module,
    batch: list[tuple[CachedFrame, CachedFrame, torch.Tensor]],
    config: TrainConfig,
    generator: torch.Generator,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Loss of one batch of ``(frame_i, frame_j, T_i_j)`` and its log values."""
    aug = AugmentConfig(
        config.aug_rotation_deg,
        config.aug_scale,
        config.aug_min_keep,
        config.crop_radius,
        config.aug_hole_prob,
        config.aug_hole_min_keep,
    )
    views = [make_pair_views(fi, fj, T, config.voxel_size, aug, generator) for fi, fj, T in batch]
    coords = [c for v in views for c in (v.view_i.coords, v.view_j.coords)]
    # bfloat16 matmuls on CPU (amp true): several times the float32 throughput where the CPU
    # has bf16 instructions; the loss stays in float32
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bool(config.amp)):
        feats = [f.float() for f in encode_views(encoder, coords)]
    losses, positives = [], []
    for n, v in enumerate(views):
        matches = sample_matches(v.matches, config.num_positives, generator)
        positives.append(len(matches))
        losses.append(pair_loss(feats[2 * n], feats[2 * n + 1], matches, v.view_i.points, config))
    loss = torch.stack(losses).mean()
    points = float(np.mean([len(c) for c in coords]))
    return loss, {
        "loss": float(loss.detach()),
        "positives": float(np.mean(positives)),
        "points": points,
    }


class SelfPosedTask:
    """The ``self-posed`` variant's encoder, pairs, step and validation (a
    :class:`~byoc_cli.training.task.TrainTask`).

    One process on the CPU. Before the first step of each round the round's pairs are loaded
    (estimated on first use, :func:`load_or_estimate_pairs`) and logged as a ``round`` record;
    the end of a round is checkpointed, so a resumed run poses the next round itself.

    Raises:
        DatasetError: no training sequence, or no pair passed verification.
    """

    fused_optimizer = True

    def __init__(self, config: TrainConfig, info: Any = None) -> None:
        from byoc_cli.models.encoder import build_encoder

        del info  # one process
        self.config = config
        self.run_dir = Path(config.out)
        self.sequences = discover_training_sequences(config)
        self.data_names = [s.name for s in self.sequences]
        self.val_pairs = validation_pairs(config) if config.val_dir else []
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            self.model = build_encoder(config.arch)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.generators = {"sample": self.generator}
        self.frames: dict[tuple[int, int], CachedFrame] = {}
        self.flat: list[tuple[int, PseudoPair]] = []
        self.round: int | None = None

    @property
    def validates(self) -> bool:
        return bool(self.val_pairs)

    def load_initial_weights(self) -> None:
        load_initial_weights(self.model, self.config)

    def data_position(self) -> dict[str, int]:
        # the pairs are drawn from ``generator``: its state is the position
        return {"epoch": 0, "batch_in_epoch": 0}

    def restore_position(self, state: dict[str, Any]) -> None:
        del state

    def prepare(self, step: int, records: Any, progress: Any = None) -> None:
        """Load the pairs of the round of the next step when it is not the loaded one
        (``progress(stage, done, total)`` hears of their pseudo-poses)."""
        number = self.config.round_of(step)
        if number == self.round:
            return
        config = self.config
        found = load_or_estimate_pairs(
            config,
            self.run_dir,
            self.sequences,
            progress,
            round_number=number,
            encoder=self.model,
        )
        pairs = [pairs_from_json(r) for r in found]
        flat = [(s, p) for s, seq_pairs in enumerate(pairs) for p in seq_pairs]
        if not flat:
            gaps = ", ".join(map(str, config.pair_gaps))
            raise DatasetError(
                ", ".join(config.rgbd_dir),
                f"no self-posed pair passed verification (round {number}): give longer "
                f"sequences, or smaller frame gaps (pair_gaps in --config, now {gaps})",
            )
        self.frames = build_frame_cache(config, self.sequences, pairs, self.frames, progress)
        logged = records.read()
        if not any(r.get("kind") == "round" and r.get("round") == number for r in logged):
            records.write(round_record(number, step, found))
        self.flat, self.round = flat, number

    def next_batch(self) -> list[tuple[CachedFrame, CachedFrame, torch.Tensor]]:
        """``batch_size`` pairs drawn with replacement: ``(frame_i, frame_j, T_i_j)``."""
        pick = torch.randint(len(self.flat), (self.config.batch_size,), generator=self.generator)
        batch = []
        for k in pick.tolist():
            s, pair = self.flat[k]
            frames = self.frames[(s, pair.i)], self.frames[(s, pair.j)]
            batch.append((*frames, torch.from_numpy(pair.T_i_j)))
        return batch

    def step(self, module: torch.nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        return training_step(module, batch, self.config, self.generator)

    def summarize(self, window: list[dict[str, float]], seconds: float) -> dict[str, float]:
        mean = {k: float(np.mean([w[k] for w in window])) for k in window[0]}
        pairs = len(window) * self.config.batch_size
        return {**mean, "pairs_per_s": pairs / seconds if seconds else None}

    def validate(self) -> dict[str, float] | None:
        if not self.val_pairs:
            return None
        config = self.config
        return feature_match_validation(self.model, self.val_pairs, config.voxel_size, config.seed)

    def checkpoint_due(self, step: int) -> bool:
        """The end of a round."""
        return bool(self.config.round_steps) and step % self.config.round_steps == 0

    def export(self, path: Path, steps: int, metrics: dict[str, float]) -> str:
        return export_encoder(self.model, self.config, path, self.data_names, steps, metrics)
