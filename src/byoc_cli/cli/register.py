"""``byoc register SOURCE TARGET``: write the transform that maps SOURCE into TARGET's frame."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import click

from byoc_cli.cli.errors import EXIT_LOW_CONFIDENCE, handle_errors
from byoc_cli.cli.options import (
    device_option,
    features_option,
    finite_float,
    float_option,
    int_option,
    path_option,
    resolve_device,
    seed_option,
    voxel_size_option,
    weights_option,
)
from byoc_cli.cli.output import claim_outputs, is_stdout, write_json, write_stdout
from byoc_cli.pipeline.register import FEATURE_DEFAULTS

log = logging.getLogger("byoc")

DEPTH_EXTENSIONS = (".png", ".tif", ".tiff")


def _load_cloud(path: Path, intrinsics: Path | None, depth_scale: float, scale: float | None):
    """Read one input as float64 metres; returns ``(points (N,3) tensor, note)``."""
    import torch

    from byoc_cli.io import check_units, read_depth_cloud, read_point_cloud

    if path.suffix.lower() in DEPTH_EXTENSIONS:
        loaded = read_depth_cloud(path, intrinsics, depth_scale=depth_scale)
    else:
        loaded = read_point_cloud(path)
    if loaded.num_nonfinite_dropped:
        log.warning(
            "%s: dropped %d point(s) with NaN/Inf coordinates", path, loaded.num_nonfinite_dropped
        )
    points = loaded.points
    if scale is None:
        check_units(points, path)
    else:
        points = points * scale
    return torch.from_numpy(points)


def _make_extractor(features: str, weights: Path | None, voxel_size: float | None, device: str):
    """Build the feature extractor; returns ``(extractor, weights_info | None)``."""
    from byoc_cli.pipeline.features import ByocExtractor, FpfhExtractor

    if features == "fpfh":
        return FpfhExtractor(voxel_size or FEATURE_DEFAULTS["fpfh"]["voxel_size"]), None
    from byoc_cli.pipeline.weights import load_weights

    if weights is None:
        from byoc_cli.pipeline.default_weights import default_weights_path, load_default_weights

        path = default_weights_path()
        if path is None:
            raise click.UsageError(
                "--features byoc needs --weights PATH (this install ships no trained weights); "
                "or use --features fpfh"
            )
        loaded = load_default_weights()
    else:
        path = weights
        loaded = load_weights(path)
    trained_voxel = float(loaded.metadata["voxel_size"])
    if voxel_size is not None and abs(voxel_size - trained_voxel) > 1e-9:
        log.warning(
            "--voxel-size %g differs from the %g m the weights were trained at",
            voxel_size,
            trained_voxel,
        )
    info = {
        "path": str(path),
        "sha256": loaded.file_sha256,
        "architecture": loaded.metadata["architecture"],
        "variant": loaded.metadata["training"]["variant"],
        "code_version": loaded.metadata["code_version"],
    }
    return ByocExtractor(loaded.encoder, voxel_size or trained_voxel, device), info


def _unscale(T, scale: float | None):
    """Back to the input units: a transform found on ``s * x`` has translation ``t / s``."""
    T = T.clone()
    if scale is not None:
        T[:3, 3] /= scale
    return T


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
    help="Write the source, transformed into the target frame, as binary PLY.",
)
@path_option(
    "--json",
    "json_path",
    dash=True,
    default=None,
    help="Write a JSON report ('-' is stdout, then T goes only to -o).",
)
@features_option
@weights_option
@voxel_size_option
@click.option(
    "--estimator",
    type=click.Choice(["auto", "procrustes", "ransac"]),
    default="auto",
    show_default=True,
    help="Randomized weighted Procrustes (the paper's) or RANSAC; "
    "auto: ransac for both feature types (README: defaults for learned features).",
)
@click.option(
    "--refine",
    type=click.Choice(["auto", "none", "icp"]),
    default="auto",
    show_default=True,
    help="Refine with point-to-plane ICP (open3d); auto: the feature type's default (none).",
)
@int_option(
    "--max-points",
    help="Seeded random subset of kept points per cloud that enters matching (0 = all) "
    "[default: 5000 with byoc features, 10000 with fpfh].",
)
@int_option(
    "--num-correspondences",
    min=3,
    help="Top-k ratio-test matches kept per direction [default: 200 for byoc, 1000 for fpfh].",
)
@float_option(
    "--min-confidence",
    type=finite_float(0, 1),
    default=0.0,
    help="Exit 3 when the confidence is below this.",
)
@float_option(
    "--scale",
    help="Multiply input coordinates by this (0.001 for millimetres); disables the "
    "unit check. T is written in the input units.",
)
@path_option(
    "--intrinsics",
    help="For depth-image inputs: Open3D intrinsics JSON or a 3x3 text matrix.",
)
@float_option(
    "--depth-scale", default=1000.0, help="Depth-image units per metre (1000 = mm, 5000 = TUM)."
)
@seed_option
@device_option
@handle_errors
def register(
    source: Path,
    target: Path,
    output: Path,
    aligned: Path | None,
    json_path: Path | None,
    features: str,
    weights: Path | None,
    voxel_size: float | None,
    estimator: str,
    refine: str,
    max_points: int | None,
    num_correspondences: int | None,
    min_confidence: float,
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
    for path in (source, target):
        if path.suffix.lower() in DEPTH_EXTENSIONS and intrinsics is None:
            raise click.BadParameter(
                f"{path} is a depth image: --intrinsics is required", param_hint="'--intrinsics'"
            )
    outputs = claim_outputs(
        {"-o": output, "--aligned": aligned, "--json": json_path},
        inputs=(source, target, intrinsics, weights),
    )
    defaults = FEATURE_DEFAULTS[features]
    if estimator == "auto":
        estimator = defaults["estimator"]
    if refine == "auto":
        refine = defaults["refine"] or "none"
    if num_correspondences is None:
        num_correspondences = defaults["num_correspondences"]
    if max_points is None:
        max_points = defaults["max_points"]
    from byoc_cli import __version__
    from byoc_cli.geometry import apply_transform
    from byoc_cli.io import atomic_write_text, format_transform, write_ply
    from byoc_cli.pipeline.register import RegisterConfig, register_clouds

    extractor, weights_info = _make_extractor(features, weights, voxel_size, device)
    t0 = time.perf_counter()
    points_src = _load_cloud(source, intrinsics, depth_scale, scale)
    points_tgt = _load_cloud(target, intrinsics, depth_scale, scale)
    load_time = time.perf_counter() - t0
    config = RegisterConfig(
        num_correspondences=num_correspondences,
        max_points=max_points,
        estimator=estimator,
        refine=None if refine == "none" else "icp",
        seed=seed,
    )
    result = register_clouds(
        points_src, points_tgt, extractor, config, labels=(str(source), str(target))
    )
    T = _unscale(result.T_tgt_src, scale)
    passed = result.confidence >= min_confidence

    timings = {"load": load_time, **result.timings, "command": time.perf_counter() - started}
    report = {
        "source": str(source),
        "target": str(target),
        "T_tgt_src": T.tolist(),
        "convention": "x_tgt = R x_src + t; T is 4x4 on column vectors",
        "features": extractor.name,
        "estimator": estimator,
        "refine": refine,
        "num_points_src": result.num_points_src,
        "num_points_tgt": result.num_points_tgt,
        "num_correspondences": result.num_correspondences,
        "num_inliers": result.num_inliers,
        "inlier_ratio": result.inlier_ratio,
        "inlier_threshold_m": result.inlier_threshold,
        "overlap": result.overlap,
        "confidence": result.confidence,
        "min_confidence": min_confidence,
        "passed": passed,
        "voxel_size_m": extractor.voxel_size,
        "scale": scale,
        "max_points": max_points,
        "seed": seed,
        "device": device,
        "weights": weights_info,
        "weights_sha256": weights_info["sha256"] if weights_info else None,
        "byoc_cli_version": __version__,
        "timings_s": timings,
    }

    with outputs:  # every file is committed at the end of the block, or none
        if aligned is not None:
            write_ply(aligned, apply_transform(T, points_src / (scale or 1.0)).numpy())
        write_json(json_path, report)
        if is_stdout(output):
            write_stdout(format_transform(T.numpy()))
        elif output is not None:
            atomic_write_text(output, format_transform(T.numpy()))
    log.info(
        "registered %s -> %s: confidence %.3f, %d/%d inliers, %.2f s",
        source,
        target,
        result.confidence,
        result.num_inliers,
        result.num_correspondences,
        timings["command"],
    )
    if not passed:
        click.echo(
            f"byoc: confidence {result.confidence:.3f} is below --min-confidence {min_confidence}",
            err=True,
        )
        raise SystemExit(EXIT_LOW_CONFIDENCE)


def _stdout_output(output: Path, json_path: Path | None) -> Path | None:
    """``-o``: None when only ``--json -`` was asked for (the default ``-o -`` then yields)."""
    from click.core import ParameterSource

    if not (is_stdout(output) and is_stdout(json_path)):
        return output
    source = click.get_current_context().get_parameter_source("output")
    if source is ParameterSource.DEFAULT:
        return None
    raise click.UsageError("-o and --json cannot both be stdout")
