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

The run folder, checkpoints, metrics and exported weights follow the other variants
(:mod:`byoc_cli.training.trainer`).
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
from byoc_cli.training.checkpoint import (
    capture_rng_state,
    load_latest_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from byoc_cli.training.config import TrainConfig
from byoc_cli.training.guard import check_finite, step_guard
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


def round_of(step: int, config: TrainConfig) -> int:
    """The round (from 1) that the step after ``step`` completed steps belongs to."""
    return 1 + step // config.round_steps if config.round_steps else 1


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
) -> dict[tuple[int, int], CachedFrame]:
    """``(sequence, frame) -> CachedFrame`` for every frame of a kept pair (frames already in
    ``cache``, e.g. an earlier round's, are not read again)."""
    cache = dict(cache or {})
    voxel = CACHE_VOXEL_FACTOR * config.voxel_size
    for s, (sequence, seq_pairs) in enumerate(zip(sequences, pairs, strict=True)):
        for f in sorted({p.i for p in seq_pairs} | {p.j for p in seq_pairs}):
            if (s, f) not in cache:
                cache[(s, f)] = cache_frame(frame_points(sequence, f), voxel)
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


def build_optimizer(encoder: torch.nn.Module, config: TrainConfig) -> torch.optim.Adam:
    """Adam with the config's lr, eps and weight decay, fused (one kernel for all tensors:
    a quarter of the for-loop Adam's time on a compact encoder's 6.5 M parameters)."""
    return torch.optim.Adam(
        encoder.parameters(),
        lr=config.lr,
        eps=config.adam_eps,
        weight_decay=config.weight_decay,
        fused=True,
    )


def train_self_posed(config: TrainConfig, resume: bool, callbacks: Any) -> Any:
    """Train (or continue) a ``self-posed`` run; returns a ``trainer.TrainResult``."""
    from byoc_cli.models.encoder import build_encoder
    from byoc_cli.training.plot import plot_metrics, read_metrics
    from byoc_cli.training.run_folder import (
        WEIGHTS_FILE,
        load_initial_weights,
        start_run_folder,
        truncate_metrics,
        write_run_config,
    )
    from byoc_cli.training.trainer import METRICS_FILE, PLOT_FILE, StepInfo, TrainResult

    run_dir = Path(config.out)
    if not resume:
        start_run_folder(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    sequences = discover_training_sequences(config)
    data_names = [s.name for s in sequences]
    write_run_config(run_dir, config, {"world_size": 1, "data": data_names})
    val_pairs = validation_pairs(config) if config.val_dir else []

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        encoder = build_encoder(config.arch)
    optimizer = build_optimizer(encoder, config)
    generator = torch.Generator().manual_seed(config.seed)
    generators = {"sample": generator}
    step = 0
    if resume:
        found = load_latest_checkpoint(run_dir)
        if found is not None:
            state, _ = found
            encoder.load_state_dict(state["model"])
            optimizer.load_state_dict(state["optimizer"])
            step = int(state["step"])
            restore_rng_state(state["rng"][0], generators)
    if step == 0:
        load_initial_weights(encoder, config)
    metrics_path = run_dir / METRICS_FILE
    truncate_metrics(metrics_path, step)
    result = TrainResult(run_dir, None, None, step)

    def write_record(record: dict[str, Any]) -> None:
        with open(metrics_path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(record, sort_keys=True) + "\n")

    def run_validation(at_step: int) -> dict[str, float]:
        if not val_pairs:
            return {}
        t0 = time.perf_counter()
        metrics = feature_match_validation(encoder, val_pairs, config.voxel_size, config.seed)
        metrics["val_time_s"] = time.perf_counter() - t0
        write_record({"kind": "val", "step": at_step, **metrics})
        callbacks.call("on_validation", at_step, metrics)
        return metrics

    frames: dict[tuple[int, int], CachedFrame] = {}

    def load_round(number: int) -> list[tuple[int, PseudoPair]]:
        nonlocal frames
        records = load_or_estimate_pairs(
            config, run_dir, sequences, round_number=number, encoder=encoder
        )
        pairs = [pairs_from_json(r) for r in records]
        flat = [(s, p) for s, seq_pairs in enumerate(pairs) for p in seq_pairs]
        if not flat:
            gaps = ", ".join(map(str, config.pair_gaps))
            raise DatasetError(
                ", ".join(config.rgbd_dir),
                f"no self-posed pair passed verification (round {number}): give longer "
                f"sequences, or smaller frame gaps (pair_gaps in --config, now {gaps})",
            )
        frames = build_frame_cache(config, sequences, pairs, frames)
        logged = read_metrics(metrics_path) if metrics_path.exists() else []
        if not any(r.get("kind") == "round" and r.get("round") == number for r in logged):
            write_record(round_record(number, step, records))
        return flat

    def checkpoint(at_step: int) -> None:
        state = {
            "model": encoder.state_dict(),
            "optimizer": optimizer.state_dict(),
            "step": at_step,
            "epoch": 0,
            "batch_in_epoch": 0,
            "rng": [capture_rng_state(generators)],
            "config": config.to_dict(),
            "world_size": 1,
        }
        path = save_checkpoint(run_dir, at_step, state, keep=config.keep_checkpoints)
        callbacks.call("on_checkpoint", at_step, path)

    current_round = round_of(step, config)
    flat = load_round(current_round)
    callbacks.call("on_start", step, config.steps)
    if config.val_every and step == 0:
        result.initial_validation = result.validation = run_validation(0)
    encoder.train()
    window: list[dict[str, float]] = []
    t_window = time.perf_counter()
    try:
        while step < config.steps:
            if round_of(step, config) != current_round:
                current_round = round_of(step, config)
                flat = load_round(current_round)
            pick = torch.randint(len(flat), (config.batch_size,), generator=generator)
            batch = []
            for k in pick.tolist():
                s, pair = flat[k]
                batch.append(
                    (frames[(s, pair.i)], frames[(s, pair.j)], torch.from_numpy(pair.T_i_j))
                )
            with step_guard(encoder, step + 1, config.lr):
                loss, values = training_step(encoder, batch, config, generator)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                check_finite(loss, encoder.parameters(), step + 1, config.lr)
            step += 1
            window.append(values)
            last = step == config.steps
            elapsed = time.perf_counter() - t_window
            rate = len(window) / elapsed if elapsed > 0 else 0.0
            eta = (config.steps - step) / rate if rate > 0 else float("nan")
            callbacks.call(
                "on_step", StepInfo(step, config.steps, {"loss": values["loss"]}, rate, eta)
            )
            if (config.log_every and step % config.log_every == 0) or last:
                mean = {k: float(np.mean([w[k] for w in window])) for k in window[0]}
                record = {
                    "kind": "train",
                    "step": step,
                    **mean,
                    "pairs_per_s": len(window) * config.batch_size / elapsed if elapsed else None,
                    "steps_per_s": rate,
                    "lr": config.lr,
                    "time": time.time(),
                }
                write_record(record)
                callbacks.call("on_log", record)
                window, t_window = [], time.perf_counter()
            if config.val_every and (step % config.val_every == 0 or last):
                result.validation = run_validation(step)
                plot_metrics(read_metrics(metrics_path), run_dir / PLOT_FILE, "self-posed")
            round_end = config.round_steps and step % config.round_steps == 0
            if (
                (config.checkpoint_every and step % config.checkpoint_every == 0)
                or last
                or round_end
            ):
                checkpoint(step)
    except KeyboardInterrupt:
        if step > 0:
            checkpoint(step)
        raise
    result.steps = step
    records = read_metrics(metrics_path)
    train_records = [r for r in records if r.get("kind") == "train"]
    if train_records:
        result.first_loss = train_records[0]["loss"]
        result.last_loss = train_records[-1]["loss"]
    plot_metrics(records, run_dir / PLOT_FILE, "self-posed")
    export = {"train_loss": result.last_loss} if result.last_loss is not None else {}
    export.update({f"val_{k}": v for k, v in result.validation.items() if k != "val_time_s"})
    result.weights_path = run_dir / WEIGHTS_FILE
    result.weights_sha256 = export_encoder(
        encoder, config, result.weights_path, data_names, step, export
    )
    return result
