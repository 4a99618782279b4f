"""``byoc weights``: inspect and create weights files (see weights-spec/)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import click

from byoc_cli.cli.errors import handle_errors
from byoc_cli.cli.options import SEED, VOXEL, float_option, path_option
from byoc_cli.cli.output import (
    check_binary_stdout,
    claim_outputs,
    is_stdout,
    write_json,
    write_stdout,
    write_stdout_bytes,
)


@click.group("weights")
def weights() -> None:
    """Inspect or create weights files (safetensors + JSON metadata, weights-spec/)."""


@weights.command("info")
@click.argument("path", type=click.Path(path_type=Path), required=False)
@handle_errors
def info(path: Path | None) -> None:
    """Validate PATH against the weights spec and print its metadata as JSON on stdout.

    Without PATH: the weights that ship with byoc-cli (checksum verified).
    """
    from byoc_cli.pipeline.weights import load_weights

    if path is None:
        from byoc_cli.pipeline.default_weights import default_weights_path, load_default_weights

        if default_weights_path() is None:
            raise click.UsageError("this install ships no trained weights: name a weights FILE")
        loaded = load_default_weights()
    else:
        loaded = load_weights(path)
    out = dict(loaded.metadata)
    out["shipped"] = path is None
    out["path"] = loaded.path
    out["file_sha256"] = loaded.file_sha256
    out["num_parameters"] = sum(p.numel() for p in loaded.encoder.parameters())
    write_json(Path("-"), out, sort_keys=True)


@weights.command("init")
@click.option("--arch", default="compact", show_default=True, help="Encoder architecture name.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seeds the initialisation.")
@float_option(
    "--voxel-size", type=VOXEL, default=0.025, help="Voxel size (m) recorded in the metadata."
)
@path_option(
    "-o", "--output", required=True, dash=True, help="The weights file to write ('-' is stdout)."
)
@handle_errors
def init(arch: str, seed: int, voxel_size: float, output: Path) -> None:
    """Write a randomly initialised encoder (variant random-init) to OUTPUT.

    For benchmarks and tests: random features register poorly.
    """
    from byoc_cli.models.encoder import ENCODER_CONFIGS
    from byoc_cli.pipeline.weights import init_weights, save_weights, weights_bytes

    if arch not in ENCODER_CONFIGS:
        raise click.BadParameter(
            f"unknown architecture {arch!r} (known: {', '.join(sorted(ENCODER_CONFIGS))})",
            param_hint="'--arch'",
        )
    check_binary_stdout(output, "-o")
    with claim_outputs({"-o": output}):
        encoder, meta = init_weights(arch, seed, voxel_size)
        if is_stdout(output):  # the file on stdout; its name and digest go to stderr
            blob = weights_bytes(output, encoder, meta)
            write_stdout_bytes(blob)
            click.echo(f"byoc: -\t{hashlib.sha256(blob).hexdigest()}", err=True)
            return
        digest = save_weights(output, encoder, meta)
        write_stdout(f"{output}\t{digest}\n")
