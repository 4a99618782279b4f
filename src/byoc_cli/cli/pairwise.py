"""What the commands that register many pairs share: ``byoc register``'s pairwise registration
(its extractor and its settings for the features) and progress bars per stage.

``register-scans`` and ``odometry`` build on this module, so that no command module imports
another.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.display import is_quiet, progress_bar

log = logging.getLogger("byoc")


def registrar(
    features: str,
    weights: Path | None,
    voxel_size: float | str | None,
    device: str,
    fallback: str = "none",
    min_confidence: float | None = None,
):
    """The API's :class:`~byoc_cli.api.Registrar` for a command's options (``fallback``
    runs below ``min_confidence``, with byoc features only).

    Raises:
        click.UsageError: byoc features, no ``--weights`` and no shipped weights.
    """
    from byoc_cli.api import Registrar
    from byoc_cli.pipeline.default_weights import default_weights_path

    if features == "fpfh" and weights is not None:
        log.warning("--weights %s is not used: --features fpfh needs no weights", weights)
    if features == "byoc" and weights is None and default_weights_path() is None:
        raise click.UsageError(
            "--features byoc needs --weights PATH (this install ships no trained weights); "
            "or use --features fpfh"
        )
    use = fallback if fallback != "none" and features == "byoc" else None
    return Registrar(
        features, weights, voxel_size, device, fallback=use, fallback_below=min_confidence
    )


def pairwise_setup(
    features: str, weights: Path | None, voxel_size: float | None, device: str, seed: int
) -> tuple[Any, Any, dict | None]:
    """The extractor and settings of ``byoc register`` for ``features``.

    Returns:
        ``(extractor, RegisterConfig, weights_info | None)``.
    """
    from byoc_cli.pipeline.register import FEATURE_DEFAULTS, RegisterConfig

    made = registrar(features, weights, voxel_size, device)
    defaults = FEATURE_DEFAULTS[features]
    config = RegisterConfig(
        num_correspondences=defaults["num_correspondences"],
        max_points=defaults["max_points"],
        estimator=defaults["estimator"],
        seed=seed,
    )
    return made.extractor, config, made.weights_info


class StageProgress:
    """Progress bars on stderr per stage (only on a terminal and without -q)."""

    def __init__(self, quiet: bool) -> None:
        import sys

        self.progress = progress_bar() if not is_quiet(quiet) and sys.stderr.isatty() else None
        self.tasks: dict[str, Any] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if self.progress is None:
            return
        if stage not in self.tasks:
            self.tasks[stage] = self.progress.add_task(stage, total=total)
        self.progress.update(self.tasks[stage], completed=done)

    def close(self) -> None:
        if self.progress is not None:
            self.progress.__exit__(None, None, None)
