"""``byoc train``: learn registration features from RGB-D (or depth-only) video, no poses."""

from __future__ import annotations

import logging
import math
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.display import is_quiet, progress_bar
from byoc_cli.cli.errors import handle_errors
from byoc_cli.cli.options import (
    DEPTH_SCALE,
    DEVICES,
    LEARNING_RATE,
    SEED,
    VOXEL,
    apply,
    choice_option,
    float_option,
    int_option,
    path_option,
    quiet_option,
    verbose_option,
)
from byoc_cli.cli.output import write_stdout
from byoc_cli.io.folders import check_run_folder
from byoc_cli.training.config import VARIANTS

log = logging.getLogger("byoc")


def is_run_folder(folder: Path) -> bool:
    """True when ``folder`` holds the ``config.json`` byoc writes into a run folder."""
    from byoc_cli.errors import InputError
    from byoc_cli.io.inputs import read_json_input

    try:
        doc = read_json_input(folder / "config.json", "config")
    except InputError:
        return False
    return isinstance(doc, dict) and "byoc_cli_version" in doc and "config" in doc


def _fmt(value: float | None, spec: str = ".4f") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return format(value, spec)


def _validation_summary(start: dict[str, float], end: dict[str, float]) -> str:
    """First and last validation figures of a run: pose accuracy for the paper's variants,
    feature-match recall for ``self-posed`` (its validation measures that); "-" where a
    figure is missing (a resumed run has no start)."""
    if "fmr" in end:
        first, second = ("fmr", "feature-match recall"), ("inlier_ratio", "inlier ratio")
        scale = 100.0
    else:
        first, second = ("rot_acc_5", "rot@5deg"), ("inlier_pct_mean", "inlier correspondences")
        scale = 1.0

    def pct(metrics: dict[str, float], key: str) -> str:
        value = metrics.get(key)
        return _fmt(None if value is None else scale * value, ".1f")

    return (
        f"validation {first[1]} {pct(start, first[0])}% (start) -> {pct(end, first[0])}% "
        f"(end); {second[1]} {pct(start, second[0])}% -> {pct(end, second[0])}%"
    )


def _loss_text(losses: dict[str, float]) -> str:
    """``loss X vis Y geo Z v2g W`` (the terms a variant has)."""
    parts = [f"loss {losses['loss']:.4f}"]
    for key in ("vis", "geo", "v2g"):
        value = losses.get(f"loss_{key}")  # the self-posed variant has one loss
        if value:
            parts.append(f"{key} {value:.4f}")
    return " ".join(parts)


#: how each stage of the work before the first step is named
_STAGES = {
    "frames": "self-posed pairs: reading frames",
    "odometry": "self-posed pairs: odometry",
    "pairs": "self-posed pairs: registering pairs",
    "cache": "caching the frames of the pairs",
}


class _Display:
    """Progress on stderr: a rich bar on a terminal, plain lines otherwise (a log file, a
    pipe), nothing with ``-q`` (errors only).

    The bar shows the losses averaged since the last metrics line, then that line's own
    figures: the figures of ``metrics.jsonl`` and of the closing summary. The work before the
    first step (``self-posed``: its pseudo-poses) is shown per stage, so that no run is
    silent for minutes.
    """

    #: seconds between two plain lines of one stage
    LINE_EVERY_S = 10.0

    def __init__(self, quiet: bool, bar: bool) -> None:
        self.quiet = quiet
        self.bar = bar and not quiet
        self.progress = None
        self.task = None
        self.window: list[dict[str, float]] = []
        self.stages: dict[str, Any] = {}  # stage -> its bar task, or the time of its last line

    def __enter__(self) -> _Display:
        if self.bar:
            self.progress = progress_bar("{task.fields[losses]}", "{task.fields[rate]} steps/s")
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.progress is not None:
            self.progress.__exit__(*exc)

    def echo(self, text: str) -> None:
        if self.quiet:
            return
        if self.progress is not None:
            self.progress.console.print(text, markup=False, highlight=False)
        else:
            click.echo(f"byoc: {text}", err=True)

    # callbacks ---------------------------------------------------------------
    def on_stage(self, stage: str, done: int, total: int) -> None:
        label = _STAGES.get(stage, stage)
        if self.progress is not None:
            if stage not in self.stages:
                self.stages[stage] = self.progress.add_task(label, total=total, losses="", rate="-")
            self.progress.update(self.stages[stage], completed=done, total=total)
            return
        now = time.monotonic()
        last = self.stages.get(stage)
        if last is None or done == total or now - last >= self.LINE_EVERY_S:
            self.stages[stage] = now
            self.echo(f"{label} {done}/{total}")

    def on_start(self, step: int, total: int) -> None:
        if self.progress is not None:
            self.task = self.progress.add_task(
                "train", total=total, completed=step, losses="", rate="-"
            )
        else:
            self.echo(f"training from step {step} to {total}")

    def on_step(self, info) -> None:
        if self.progress is None or self.task is None:
            return
        self.window.append(info.losses)
        mean = {k: sum(w.get(k, 0.0) for w in self.window) / len(self.window) for k in info.losses}
        self.progress.update(
            self.task, completed=info.step, losses=_loss_text(mean), rate=f"{info.steps_per_s:.2f}"
        )

    def on_log(self, record: dict) -> None:
        self.window = []
        if self.progress is not None and self.task is not None:
            self.progress.update(self.task, losses=_loss_text(record))
            return
        terms = " ".join(
            f"{k.removeprefix('loss_')} {_fmt(record.get(k))}"
            for k in ("loss_vis", "loss_geo", "loss_v2g")
            if record.get(k)
        )
        self.echo(
            f"step {record['step']}: loss {_fmt(record['loss'])} {terms} "
            f"({_fmt(record.get('steps_per_s'), '.2f')} steps/s)"
        )

    def on_validation(self, step: int, metrics: dict) -> None:
        if "rot_acc_5" not in metrics:  # the self-posed variant's feature-match validation
            self.echo(
                f"validation at step {step} ({int(metrics.get('num_pairs', 0))} pairs): "
                f"feature-match recall {_fmt(100 * metrics['fmr'], '.1f')}%, inlier ratio "
                f"{_fmt(100 * metrics['inlier_ratio'], '.1f')}%"
            )
            return
        self.echo(
            f"validation at step {step} ({int(metrics.get('num_pairs', 0))} pairs): rotation "
            f"{_fmt(metrics['rot_acc_5'], '.1f')}/{_fmt(metrics['rot_acc_10'], '.1f')}/"
            f"{_fmt(metrics['rot_acc_45'], '.1f')}% at 5/10/45 deg, median "
            f"{_fmt(metrics['rot_median_deg'], '.2f')} deg; translation "
            f"{_fmt(metrics['trans_acc_5'], '.1f')}/{_fmt(metrics['trans_acc_10'], '.1f')}/"
            f"{_fmt(metrics['trans_acc_25'], '.1f')}% at 5/10/25 cm, median "
            f"{_fmt(metrics['trans_median_cm'], '.1f')} cm; inlier correspondences "
            f"{_fmt(metrics.get('inlier_pct_mean'), '.1f')}%"
        )

    def on_checkpoint(self, step: int, path: Path) -> None:
        if self.progress is None:
            self.echo(f"checkpoint {path}")


def _loss_summary(result) -> str:
    """The losses of the closing line: the first and last metrics lines' means, or the one
    line's when the run logged once."""
    if result.loss_lines <= 1:
        return f"loss {_fmt(result.last_loss)} (the mean of its one metrics line)"
    return (
        f"loss {_fmt(result.first_loss)} -> {_fmt(result.last_loss)} (means of the first and "
        f"last of {result.loss_lines} metrics lines)"
    )


def _explicit(ctx: click.Context, values: dict[str, Any]) -> dict[str, Any]:
    """Flags given on the command line (or in the environment), by config key."""
    from click.core import ParameterSource

    out = {}
    for key, value in values.items():
        source = ctx.get_parameter_source(key)
        if (
            source in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT)
            and value is not None
        ):
            if isinstance(value, tuple) and not value:
                continue
            if isinstance(value, Path):
                value = str(value)
            elif isinstance(value, tuple):
                value = tuple(str(v) for v in value)
            out[key] = value
    return out


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _interrupt_on_sigterm() -> None:
    """Let SIGTERM (a scheduler, ``kill``) end training as Ctrl-C does: checkpoint, then stop.

    Under torchrun the launcher owns the workers' signals and no checkpoint is written on
    interruption (ranks could disagree on the step); the last periodic checkpoint stands.
    """
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_interrupt)


#: (option, minimum, help) of the integer settings; None defaults mean "from the config".
_COUNTS = (
    ("--steps", 1, "Optimiser steps [default: 4900 for self-posed, 200000 for the others]."),
    ("--batch-size", 1, "Pairs per step over all processes [default: 2 for self-posed, else 8]."),
    (
        "--view-spacing",
        1,
        "Frames between the views of a training pair, paper variants [default: 20].",
    ),
    ("--val-spacing", 1, "Frames between validation frames [default: 20]."),
    ("--val-every", 0, "Validate every N steps, 0 = never [default: 5000]."),
    ("--val-max-pairs", 0, "At most N validation pairs, evenly spread, 0 = all [default: 0]."),
    ("--checkpoint-every", 0, "Checkpoint every N steps (and at the end) [default: 1000]."),
    ("--log-every", 0, "Metrics line every N steps [default: 10]."),
    ("--num-workers", 0, "Data-loading worker processes [default: 2]."),
)

#: on/off switches whose default depends on the device.
_SWITCHES = (
    (
        "--amp/--no-amp",
        "Mixed precision (bfloat16) for the encoders on CUDA [default: on with CUDA].",
    ),
    (
        "--deterministic/--no-deterministic",
        "Deterministic kernels (bit-exact resume; slower) [default: on for CPU].",
    ),
)


def _blame_file(
    message: str, path: Path | None, file_values: dict | None, explicit: dict[str, Any]
) -> str:
    """Prefix a range error with the config file when a key it names came from that file."""
    if path is None or not file_values:
        return message
    from_file = {k for k in file_values if k not in explicit}
    named = set(re.findall(r"[a-z][a-z0-9_]*", message))
    return f"{path}: {message}" if from_file & named else message


@click.command(
    "train",
    epilog="Settings: built-in defaults < --config FILE (TOML, same key names with "
    "underscores) < flags. Exit codes: 0 trained; 1 bad data or runtime error; 2 usage error. "
    "Multi-process: torchrun --nproc-per-node N -m byoc_cli.cli.main train ...",
)
@path_option(
    "--rgbd-dir",
    file=False,
    multiple=True,
    help="RGB-D video folder(s) to train on (TUM, 3DMatch/7-Scenes, ScanNet, Redwood "
    "layouts); repeat for several. No poses needed.",
)
@path_option(
    "--val-dir",
    file=False,
    multiple=True,
    help="Video folder(s) with poses for validation (geometric encoder only).",
)
@path_option("--config", "config_path", help="TOML file of settings (keys as in config.json).")
@path_option(
    "--out",
    file=False,
    help="Run folder: a new or empty folder, or a byoc run folder [default: runs/byoc].",
)
@path_option(
    "--resume",
    file=False,
    help="Continue the run in this folder exactly from its newest checkpoint.",
)
@choice_option(
    "--variant",
    choices=list(VARIANTS),
    help="self-posed: depth video posed by byoc itself, a metric loss; the recipe of the "
    "shipped weights, which learns on a CPU. byoc, byoc-geo, byoc-vis, byoc-rot: the "
    "paper's, a GPU budget [default: self-posed].",
)
@click.option("--arch", help="Geometric encoder: compact | minkunet34c [default: compact].")
@click.option(
    "--init-weights",
    metavar="FILE|shipped",
    help="Start the geometric encoder from these weights (fine-tuning; 'shipped': the weights "
    "that ship with byoc; 'none': a random initialisation). Same --arch and --voxel-size "
    "[default: shipped for self-posed with the compact encoder at 0.025 m, else none].",
)
@apply(*(int_option(name, min=low, help=text) for name, low, text in _COUNTS[:2]))
@float_option("--lr", type=LEARNING_RATE, help="Adam learning rate [default: 1e-4].")
@click.option(
    "--seed",
    type=SEED,
    help="Seeds the initialisation, the data order and every random choice [default: 8].",
)
@choice_option(
    "--device",
    choices=DEVICES,
    help="Where training runs: auto (cuda when available), cpu or cuda [default: auto].",
)
@apply(*(int_option(name, min=low, help=text) for name, low, text in _COUNTS[2:]))
@float_option("--voxel-size", type=VOXEL, help="Voxel size in metres [default: 0.025].")
@path_option("--intrinsics", help="Intrinsics file for folders that ship none.")
@float_option(
    "--depth-scale",
    type=DEPTH_SCALE,
    help="Depth units per metre [default: the layout's convention].",
)
@apply(*(click.option(decls, default=None, help=text) for decls, text in _SWITCHES))
@verbose_option
@quiet_option(
    "Only errors on stderr: no progress, no summary (the weights line stays on stdout).",
    expose_value=True,
)
@click.pass_context
@handle_errors
def train(
    ctx: click.Context, config_path: Path | None, resume: Path | None, quiet: bool, **flags: Any
) -> None:
    """Train BYOC on RGB-D video without poses and export weights for
    'byoc register --weights RUN/weights.safetensors'.

    Writes RUN/config.json, RUN/metrics.jsonl, RUN/checkpoints/, RUN/training.png and
    RUN/weights.safetensors; prints the weights path and SHA-256 on stdout. RUN (--out)
    must be new, empty or a byoc run folder: a folder holding other files is refused.
    """
    from byoc_cli.cli.options import resolve_device
    from byoc_cli.training.config import load_config_file, resolve_config
    from byoc_cli.training.distributed import init_distributed, shutdown
    from byoc_cli.training.trainer import TrainCallbacks, resume_config
    from byoc_cli.training.trainer import train as run_training

    explicit = _explicit(ctx, flags)
    file_values = None
    try:
        if resume is not None:
            if config_path is not None:
                raise click.UsageError(
                    "--config cannot be combined with --resume (the run's config.json is used)"
                )
            if "out" in explicit and Path(explicit["out"]) != resume:
                raise click.UsageError("--out cannot differ from --resume")
            config = resume_config(resume, explicit)
        else:
            file_values = load_config_file(config_path) if config_path is not None else None
            config = resolve_config(file_values, explicit)
    except ValueError as exc:
        raise click.UsageError(_blame_file(str(exc), config_path, file_values, explicit)) from exc
    if not config.rgbd_dir:
        raise click.UsageError("no training data: give --rgbd-dir (or rgbd_dir in --config)")
    if config.arch:
        from byoc_cli.models.encoder import ENCODER_CONFIGS

        if config.arch not in ENCODER_CONFIGS:
            raise click.BadParameter(
                f"unknown architecture {config.arch!r} "
                f"(known: {', '.join(sorted(ENCODER_CONFIGS))})",
                param_hint="'--arch'",
            )
    resolve_device(config.device)  # usage error when cuda is asked for and absent
    if resume is None:
        check_run_folder(config.out, is_run_folder)

    info = init_distributed(config.device)
    if not info.distributed:
        _interrupt_on_sigterm()
    try:
        quiet = is_quiet(quiet) or not info.is_main
        display = _Display(quiet, bar=sys.stderr.isatty())
        with display:
            hooks = ("on_stage", "on_start", "on_step", "on_log", "on_validation")
            hooks += ("on_checkpoint",)
            callbacks = TrainCallbacks(**{hook: getattr(display, hook) for hook in hooks})
            result = run_training(config, resume=resume is not None, callbacks=callbacks, info=info)
    finally:
        shutdown(info)
    if info.is_main:
        log.info(
            "trained %d steps; loss %s -> %s",
            result.steps,
            _fmt(result.first_loss),
            _fmt(result.last_loss),
        )
        if not quiet:
            click.echo(
                f"byoc: trained {result.steps} steps in {result.run_dir}: {_loss_summary(result)}",
                err=True,
            )
        if result.validation and not quiet:
            click.echo(
                f"byoc: {_validation_summary(result.initial_validation, result.validation)}",
                err=True,
            )
        write_stdout(f"{result.weights_path}\t{result.weights_sha256}\n")
