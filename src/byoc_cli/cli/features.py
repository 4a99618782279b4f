"""``byoc features CLOUD -o feats.npz``: per-point descriptors for other solvers.

The npz holds ``points (M, 3)`` float64 (the input's coordinates times ``scale``),
``features (M, C)`` float32 (unit norm; row m describes point m), ``point_index (M,)`` int64
(rows of the input), ``voxel_size`` (in the units of ``points``), ``unit`` (``"m"`` when those
are known to be metres, else empty: :func:`features_unit`), ``scale``, ``method`` and
``weights_sha256`` (empty for fpfh). ``--npy`` writes ``<stem>.points.npy``,
``<stem>.feats.npy`` and ``<stem>.meta.json`` instead.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.errors import handle_errors
from byoc_cli.cli.options import (
    DEPTH_SCALE,
    SCALE,
    device_option,
    float_option,
    path_option,
    resolve_device,
    verbosity_options,
)
from byoc_cli.cli.output import (
    check_binary_stdout,
    claim_outputs,
    is_stdout,
    write_json,
    write_stdout_bytes,
)
from byoc_cli.cli.pairwise import DEPTH_EXTENSIONS, check_depth_inputs, registrar
from byoc_cli.cli.recipe_options import build_recipe, recipe_options

log = logging.getLogger("byoc")


def _npy_bytes(array) -> bytes:
    import numpy as np

    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def features_unit(feats, made, cloud: Path, scale_given: bool) -> str | None:
    """``"m"`` when the points of ``feats`` are known to be metres, else None (the input's own
    units): a ``--scale`` given, a depth image, a voxel given in metres or the features' own
    (the input was checked to look like metres), or an auto voxel that found a scan of the
    trained size and kept the features' voxel (as ``byoc register``'s report ``unit``)."""
    if scale_given or Path(cloud).suffix.lower() in DEPTH_EXTENSIONS or not made.auto_voxel:
        return "m"
    return "m" if (feats.refine_voxel or feats.voxel_size) == made.voxel_size else None


def _npz_bytes(feats, unit: str | None) -> bytes:
    import numpy as np

    buffer = io.BytesIO()
    np.savez(
        buffer,
        points=feats.points,
        features=feats.feats,
        point_index=feats.point_index,
        voxel_size=np.float64(feats.voxel_size),
        unit=np.str_(unit or ""),
        scale=np.float64(feats.scale),
        method=np.str_(feats.features),
        weights_sha256=np.str_(feats.weights_sha256 or ""),
    )
    return buffer.getvalue()


@click.command("features")
@click.argument("cloud", type=click.Path(path_type=Path))
@path_option(
    "-o",
    "--output",
    required=True,
    dash=True,
    help="The .npz file to write ('-' is stdout); with --npy, the stem of the .npy files "
    "(a trailing .npz is dropped).",
)
@click.option(
    "--npy",
    is_flag=True,
    help="Write <stem>.points.npy, <stem>.feats.npy and <stem>.meta.json instead of one npz.",
)
@recipe_options("recipe", "features", "weights", "voxel_size")
@float_option(
    "--scale",
    type=SCALE,
    help="Multiply input coordinates by this (0.001 for millimetres); disables the unit "
    "check. Points are written in metres.",
)
@path_option("--intrinsics", help="For a depth-image input: intrinsics JSON or 3x3 text.")
@float_option(
    "--depth-scale",
    type=DEPTH_SCALE,
    default=None,
    help="Depth-image units per metre [default: the convention of the dataset layout around "
    "the file (TUM: 5000), else 1000].",
)
@device_option
@verbosity_options
@handle_errors
def features(cloud: Path, output: Path, npy: bool, intrinsics: Path | None, **options: Any) -> None:
    """Write the kept points of CLOUD and their features (the encoder's, or FPFH) for
    TEASER++, Open3D's RANSAC or a matcher of your own (docs/pipelines.md).
    """
    from byoc_cli.io import atomic_write_bytes

    device = resolve_device(options.pop("device"))
    scale, depth_scale = options.pop("scale"), options.pop("depth_scale")
    recipe_file = options.get("recipe_path")
    recipe = build_recipe(options)
    weights = None if recipe.features.weights is None else Path(recipe.features.weights)
    check_depth_inputs((cloud,), intrinsics)
    if npy and is_stdout(output):
        raise click.BadParameter(
            "--npy writes three files: give a stem, not '-'", param_hint="'-o'"
        )
    check_binary_stdout(output, "-o")
    if npy:
        stem = output.with_suffix("") if output.suffix == ".npz" else output
        names = {
            "points": stem.with_name(stem.name + ".points.npy"),
            "feats": stem.with_name(stem.name + ".feats.npy"),
            "meta": stem.with_name(stem.name + ".meta.json"),
        }
        claimed = {f"-o ({kind})": path for kind, path in names.items()}
    else:
        claimed = {"-o": output}
    outputs = claim_outputs(claimed, inputs=(cloud, intrinsics, weights, recipe_file))
    made = registrar(recipe, device)
    feats = made.extract(cloud, scale=scale, intrinsics=intrinsics, depth_scale=depth_scale)
    unit = features_unit(feats, made, cloud, scale is not None)
    with outputs:
        if npy:
            atomic_write_bytes(names["points"], _npy_bytes(feats.points))
            atomic_write_bytes(names["feats"], _npy_bytes(feats.feats))
            write_json(
                names["meta"],
                {
                    "source": str(cloud),
                    "num_points": int(feats.points.shape[0]),
                    "feature_dim": int(feats.feats.shape[1]),
                    "voxel_size": feats.voxel_size,
                    "unit": unit,
                    "voxel_size_m": feats.voxel_size if unit == "m" else None,
                    "scale": feats.scale,
                    "method": feats.features,
                    "weights_sha256": feats.weights_sha256,
                },
            )
        elif is_stdout(output):
            write_stdout_bytes(_npz_bytes(feats, unit))
        else:
            atomic_write_bytes(output, _npz_bytes(feats, unit))
    log.info(
        "%s: %d points, %d-d %s features at %g %s",
        cloud,
        feats.points.shape[0],
        feats.feats.shape[1],
        feats.features,
        feats.voxel_size,
        unit or "input units",
    )
