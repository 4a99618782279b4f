"""``byoc register SOURCE TARGET``: write the transform that maps SOURCE into TARGET's frame."""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path

import click

from byoc_cli.cli.display import is_quiet
from byoc_cli.cli.errors import EXIT_LOW_CONFIDENCE, handle_errors
from byoc_cli.cli.options import (
    DEPTH_SCALE,
    SCALE,
    apply,
    device_option,
    features_option,
    finite_float,
    float_option,
    int_option,
    path_option,
    resolve_device,
    seed_option,
    verbosity_options,
    voxel_size_option,
    weights_option,
)
from byoc_cli.cli.output import (
    check_binary_stdout,
    claim_outputs,
    is_stdout,
    write_json,
    write_stdout,
    write_stdout_bytes,
)
from byoc_cli.cli.pairwise import registrar
from byoc_cli.pipeline.confidence import DEFAULT_MIN_CONFIDENCE

log = logging.getLogger("byoc")

DEPTH_EXTENSIONS = (".png", ".tif", ".tiff")  # byoc_cli.api.DEPTH_EXTENSIONS (no numpy here)

#: the options of one registration, shared by ``register`` and ``register-batch``
register_options = apply(
    features_option,
    weights_option,
    voxel_size_option,
    click.option(
        "--estimator",
        type=click.Choice(["auto", "procrustes", "ransac"]),
        default="auto",
        show_default=True,
        help="Randomized weighted Procrustes (the paper's) or RANSAC; "
        "auto: ransac for both feature types (README: defaults for learned features).",
    ),
    click.option(
        "--refine",
        type=click.Choice(["auto", "none", "icp", "multiscale"]),
        default="auto",
        show_default=True,
        help="icp: Open3D's point-to-plane ICP on the kept points; multiscale: coarse-to-fine "
        "point-to-plane ICP on the full clouds that holds directions the geometry leaves free; "
        "auto: multiscale for byoc features, none for fpfh.",
    ),
    int_option(
        "--max-points",
        help="Seeded random subset of kept points per cloud that enters matching (0 = all) "
        "[default: 5000 with byoc features, 10000 with fpfh].",
    ),
    int_option(
        "--num-correspondences",
        min=3,
        help="Top-k ratio-test matches kept per direction [default: 2500 for byoc, 1000 for fpfh].",
    ),
    float_option(
        "--min-confidence",
        type=finite_float(0, 1),
        default=DEFAULT_MIN_CONFIDENCE,
        help="Exit 3 when the confidence, the calibrated probability that T is right, is "
        "below this (the default keeps 95 % of the right results of the development pairs, "
        "docs/registering.md; 0 accepts every result).",
    ),
    click.option(
        "--fallback",
        type=click.Choice(["fpfh", "none"]),
        default="fpfh",
        show_default=True,
        help="With byoc features: when the confidence is below --min-confidence, register "
        "the pair again with FPFH features (same scale, same refinement) and keep the more "
        "confident result; the report says which ran (docs/registering.md). none: never.",
    ),
    float_option(
        "--scale",
        type=SCALE,
        help="Multiply input coordinates by this (0.001 for millimetres); disables the "
        "unit check. T is written in the input units.",
    ),
    path_option(
        "--intrinsics",
        help="For depth-image inputs: Open3D intrinsics JSON or a 3x3 text matrix.",
    ),
    float_option(
        "--depth-scale",
        type=DEPTH_SCALE,
        default=1000.0,
        help="Depth-image units per metre (1000 = mm, 5000 = TUM).",
    ),
    seed_option,
    device_option,
    verbosity_options,
)


#: the registrar of the command's options (one definition, in a module no command owns)
make_registrar = registrar


def match_settings(
    estimator: str, refine: str, max_points: int | None, num_correspondences: int | None, seed: int
) -> dict:
    """The :meth:`Registrar.match` keywords of the command's options (``auto`` -> None)."""
    return {
        "estimator": None if estimator == "auto" else estimator,
        "refine": None if refine == "auto" else refine,
        "max_points": max_points,
        "num_correspondences": num_correspondences,
        "seed": seed,
    }


def check_depth_inputs(paths, intrinsics: Path | None) -> None:
    """A depth-image input without ``--intrinsics`` is a usage error; ``--intrinsics`` without
    a depth-image input is not used, and a warning says so."""
    depth = [p for p in paths if Path(p).suffix.lower() in DEPTH_EXTENSIONS]
    if depth and intrinsics is None:
        raise click.BadParameter(
            f"{depth[0]} is a depth image: --intrinsics is required", param_hint="'--intrinsics'"
        )
    if intrinsics is not None and not depth:
        log.warning("--intrinsics %s is not used: no input is a depth image", intrinsics)


@click.command(
    "register",
    epilog="Exit codes: 0 registered; 1 bad input or runtime error; 2 usage error; "
    "3 registered but confidence below --min-confidence (outputs are still written).",
)
@click.argument("source", type=click.Path(path_type=Path))
@click.argument("target", type=click.Path(path_type=Path))
@path_option(
    "-o",
    "--output",
    dash=True,
    default=Path("-"),
    show_default=True,
    help="Where to write T (4 lines of 4 numbers); '-' is stdout (not written when "
    "--json - is given without -o).",
)
@path_option(
    "--aligned",
    default=None,
    dash=True,
    help="Write the source, transformed into the target frame, as binary PLY ('-' is "
    "stdout, with -o FILE).",
)
@path_option(
    "--json",
    "json_path",
    dash=True,
    default=None,
    help="Write a JSON report ('-' is stdout, then T goes only to -o).",
)
@register_options
@handle_errors
def register(
    source: Path,
    target: Path,
    output: Path,
    aligned: Path | None,
    json_path: Path | None,
    features: str,
    weights: Path | None,
    voxel_size: float | str,
    estimator: str,
    refine: str,
    max_points: int | None,
    num_correspondences: int | None,
    min_confidence: float,
    fallback: str,
    scale: float | None,
    intrinsics: Path | None,
    depth_scale: float,
    seed: int,
    device: str,
) -> None:
    """Register SOURCE onto TARGET and write T, the 4x4 transform that maps SOURCE into
    TARGET's frame: x_tgt = R x_src + t (column vectors; T = [[R, t], [0, 0, 0, 1]]).

    SOURCE and TARGET are point clouds (.ply, .pcd, .xyz, .pts, .npy of shape N x 3) in
    metres, or depth images (.png, with --intrinsics and --depth-scale).
    """
    started = time.perf_counter()
    device = resolve_device(device)
    output = _stdout_output(output, json_path)
    check_depth_inputs((source, target), intrinsics)
    check_binary_stdout(aligned, "--aligned")
    outputs = claim_outputs(
        {"-o": output, "--aligned": aligned, "--json": json_path},
        inputs=(source, target, intrinsics, weights),
    )
    from byoc_cli.api import load_cloud
    from byoc_cli.io import atomic_write_text, format_transform, write_ply

    registrar = make_registrar(features, weights, voxel_size, device, fallback, min_confidence)
    result = registrar.register(
        source,
        target,
        scale=scale,
        intrinsics=intrinsics,
        depth_scale=depth_scale,
        **match_settings(estimator, refine, max_points, num_correspondences, seed),
    )
    passed = result.confidence >= min_confidence
    report = registration_report(
        result, registrar, source, target, min_confidence, scale, device, started
    )
    T = result.T_tgt_src

    with outputs:  # every file is committed at the end of the block, or none
        if aligned is not None:
            with warnings.catch_warnings():  # read again: its warnings were shown once
                warnings.simplefilter("ignore")
                points = load_cloud(
                    source, intrinsics=intrinsics, depth_scale=depth_scale, scale=scale
                )
            moved = (points / (scale or 1.0)) @ T[:3, :3].T + T[:3, 3]
            if is_stdout(aligned):
                write_stdout_bytes(write_ply(None, moved))
            else:
                write_ply(aligned, moved)
        write_json(json_path, report)
        if is_stdout(output):
            write_stdout(format_transform(T))
        elif output is not None:
            atomic_write_text(output, format_transform(T))
    if not is_quiet(False):
        click.echo(summary_line(source, target, result, report["timings_s"]["command"]), err=True)
    if not passed:
        click.echo(
            f"byoc: confidence {result.confidence:.3f} is below --min-confidence "
            f"{min_confidence:g}: T is likely wrong (written all the same)",
            err=True,
        )
        raise SystemExit(EXIT_LOW_CONFIDENCE)


def summary_line(source: Path, target: Path, result, seconds: float) -> str:
    """The line a successful ``byoc register`` prints on stderr: confidence, inliers, the
    voxel used and the time (``-q`` silences it)."""
    line = (
        f"byoc: registered {source} -> {target}: confidence {result.confidence:.3f}, "
        f"{result.num_inliers}/{result.num_correspondences} inliers within "
        f"{100 * result.inlier_threshold:.1f} cm, voxel {result.voxel_size:g} m, {seconds:.1f} s"
    )
    if result.fallback and result.fallback["used"]:
        line += (
            f" (FPFH features: the learned ones reached confidence "
            f"{result.fallback['learned_confidence']:.3f})"
        )
    return line


def _stdout_output(output: Path, json_path: Path | None) -> Path | None:
    """``-o``: None when only ``--json -`` was asked for (the default ``-o -`` then yields)."""
    from click.core import ParameterSource

    if not (is_stdout(output) and is_stdout(json_path)):
        return output
    source = click.get_current_context().get_parameter_source("output")
    if source is ParameterSource.DEFAULT:
        return None
    raise click.UsageError("-o and --json cannot both be stdout")


def registration_report(
    result,
    registrar,
    source: Path,
    target: Path,
    min_confidence: float,
    scale: float | None,
    device: str,
    started: float,
) -> dict:
    """The JSON report of one registration (``register --json``, a line of the batch summary)."""
    from byoc_cli import __version__

    timings = {**result.timings, "command": time.perf_counter() - started}
    return {
        "source": str(source),
        "target": str(target),
        "T_tgt_src": result.T_tgt_src.tolist(),
        "convention": "x_tgt = R x_src + t; T is 4x4 on column vectors",
        "features": result.features,
        "estimator": result.estimator,
        "refine": result.refine,
        "num_points_src": result.num_points_src,
        "num_points_tgt": result.num_points_tgt,
        "num_correspondences": result.num_correspondences,
        "num_inliers": result.num_inliers,
        "inlier_ratio": result.inlier_ratio,
        "inlier_threshold_m": result.inlier_threshold,
        "overlap": result.overlap,
        "confidence": result.confidence,
        "cues": result.cues,
        "min_confidence": min_confidence,
        "passed": result.confidence >= min_confidence,
        "voxel_size_m": result.voxel_size,
        "voxel_choice": result.voxel_choice,
        "fallback": result.fallback,
        "scale": scale,
        "max_points": result.max_points,
        "seed": result.seed,
        "device": device,
        "weights": registrar.weights_info,
        "weights_sha256": result.weights_sha256,
        "byoc_cli_version": __version__,
        "timings_s": timings,
    }
