"""``byoc weights``: inspect and create weights files (see weights-spec/)."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.errors import handle_errors
from byoc_cli.cli.options import SEED, VOXEL, float_option, path_option, verbosity_options
from byoc_cli.cli.output import (
    check_binary_stdout,
    claim_outputs,
    is_stdout,
    write_json,
    write_stdout,
    write_stdout_bytes,
)


@click.group("weights")
@verbosity_options
def weights() -> None:
    """Inspect or create weights files (safetensors + JSON metadata, weights-spec/)."""


@weights.command("info")
@click.argument("path", type=click.Path(path_type=Path), required=False)
@click.option("--json", "as_json", is_flag=True, help="The metadata as JSON on stdout instead.")
@verbosity_options
@handle_errors
def info(path: Path | None, as_json: bool) -> None:
    """Validate PATH against the weights spec and describe it on stderr: architecture,
    parameters, recipe, training data, steps, validation and held-out figures, checksum.
    --json prints the whole metadata as JSON on stdout instead.

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
    if as_json:
        write_json(Path("-"), out, sort_keys=True)
    else:
        click.echo("\n".join(summary_lines(out)), err=True)


def _number(value: Any) -> str:
    """A metric as text: 4 significant digits, "-" for a missing (non-finite) value."""
    return "-" if value is None else f"{value:.4g}" if isinstance(value, float) else str(value)


def _figures(values: dict[str, Any]) -> str:
    return ", ".join(f"{name} {_number(value)}" for name, value in values.items())


def summary_lines(meta: dict[str, Any]) -> list[str]:
    """What ``byoc weights info`` prints for a file's metadata (plus ``path``, ``shipped``,
    ``file_sha256`` and ``num_parameters``): one line per topic, the topic first."""
    training = meta.get("training", {})
    metrics = dict(training.get("metrics", {}))
    validation = {k.removeprefix("val_"): metrics.pop(k) for k in list(metrics) if "val_" in k[:4]}
    origin = " (shipped with byoc-cli, checksum verified)" if meta.get("shipped") else ""
    lines = [
        f"weights     {meta['path']}{origin}",
        f"model       {meta['architecture']} encoder, {meta['num_parameters']:,} parameters, "
        f"{meta['feature_dim']}-d features, voxel {meta['voxel_size']:g} m",
        f"training    {training['variant']}, {training['steps']} steps, seed {training['seed']}",
    ]
    init = training.get("init_weights")
    if isinstance(init, dict):
        about = f": {init['description']}" if init.get("description") else ""
        lines.append(f"started at  {init.get('file')}{about} (sha256 {init.get('sha256')})")
    if isinstance(training.get("recipe"), dict):
        lines.append(f"recipe      {_figures(training['recipe'])}")
    data = training.get("data")
    lines.append(f"data        {', '.join(map(str, data)) if isinstance(data, list) else data}")
    if validation:
        names = training.get("validation_data")
        names = ", ".join(map(str, names)) if isinstance(names, list) else "posed frames"
        spacing = training.get("val_spacing")
        where = f"{names}, spacing {spacing}" if spacing else names
        lines.append(f"validation  {where}: {_figures(validation)}")
    held_out = training.get("held_out")
    if isinstance(held_out, dict):
        lines.append(f"held out    {held_out.get('protocol', '')}")
        rows = held_out.get("results")
        for row in rows if isinstance(rows, list) else []:
            if not isinstance(row, dict):
                continue
            figures = {k: v for k, v in row.items() if k != "pair_set"}
            lines.append(f"            {row.get('pair_set')}: {_figures(figures)}")
    if metrics:
        lines.append(f"metrics     {_figures(metrics)}")
    lines += [
        f"written     {meta['created']} by byoc-cli {meta['code_version']}",
        f"sha256      {meta['file_sha256']} (file), {meta['tensors_sha256']} (tensors)",
    ]
    return lines


@weights.command("init")
@click.option("--arch", default="compact", show_default=True, help="Encoder architecture name.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seeds the initialisation.")
@float_option(
    "--voxel-size", type=VOXEL, default=0.025, help="Voxel size (m) recorded in the metadata."
)
@path_option(
    "-o", "--output", required=True, dash=True, help="The weights file to write ('-' is stdout)."
)
@verbosity_options
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
