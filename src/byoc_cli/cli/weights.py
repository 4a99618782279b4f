"""``byoc weights``: inspect and create weights files (see weights-spec/)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from byoc_cli.cli.errors import handle_errors


@click.group("weights")
def weights() -> None:
    """Inspect or create weights files (safetensors + JSON metadata, weights-spec/)."""


@weights.command("info")
@click.argument("path", type=click.Path(path_type=Path))
@handle_errors
def info(path: Path) -> None:
    """Validate PATH against the weights spec and print its metadata as JSON on stdout."""
    from byoc_cli.pipeline.weights import load_weights

    loaded = load_weights(path)
    out = dict(loaded.metadata)
    out["file_sha256"] = loaded.file_sha256
    out["num_parameters"] = sum(p.numel() for p in loaded.encoder.parameters())
    click.echo(json.dumps(out, indent=2, sort_keys=True))


@weights.command("init")
@click.option("--arch", default="compact", show_default=True, help="Encoder architecture name.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option(
    "--voxel-size",
    type=click.FloatRange(min=0, min_open=True),
    default=0.025,
    show_default=True,
    help="Voxel size (m) recorded in the metadata.",
)
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True)
@handle_errors
def init(arch: str, seed: int, voxel_size: float, output: Path) -> None:
    """Write a randomly initialised encoder (variant random-init) to OUTPUT.

    For benchmarks and tests: random features register poorly.
    """
    from byoc_cli.models.encoder import ENCODER_CONFIGS
    from byoc_cli.pipeline.weights import init_weights, save_weights

    if arch not in ENCODER_CONFIGS:
        raise click.BadParameter(
            f"unknown architecture {arch!r} (known: {', '.join(sorted(ENCODER_CONFIGS))})",
            param_hint="'--arch'",
        )
    encoder, meta = init_weights(arch, seed, voxel_size)
    digest = save_weights(output, encoder, meta)
    click.echo(f"{output}\t{digest}")
