"""Options shared by several commands."""

from __future__ import annotations

from pathlib import Path

import click

voxel_size_option = click.option(
    "--voxel-size",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Voxel size in metres [default: the weights' voxel size (0.025) for byoc, 0.05 for fpfh].",
)
seed_option = click.option(
    "--seed",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Seeds every random choice; the same seed gives the same result.",
)
device_option = click.option(
    "--device",
    type=click.Choice(["auto", "cpu", "cuda"]),
    default="auto",
    show_default=True,
    help="Where the encoder runs (auto: cuda when available).",
)
weights_option = click.option(
    "--weights",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Weights file (weights-spec/ format) for --features byoc.",
)
features_option = click.option(
    "--features",
    type=click.Choice(["byoc", "fpfh"]),
    default="byoc",
    show_default=True,
    help="byoc: the learned geometric encoder (needs --weights); fpfh: Open3D FPFH.",
)


def resolve_device(device: str) -> str:
    """``auto`` -> ``cuda`` when available else ``cpu``; ``cuda`` without CUDA is a usage error."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise click.BadParameter("CUDA is not available on this machine", param_hint="'--device'")
    return device


def packaged_weights() -> Path | None:
    """The weights file shipped inside the package, if this version ships one."""
    path = Path(__file__).resolve().parents[1] / "data" / "weights" / "default.safetensors"
    return path if path.is_file() else None
