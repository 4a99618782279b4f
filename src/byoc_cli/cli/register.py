"""``byoc register SOURCE TARGET``: write the transform that maps SOURCE into TARGET's frame."""

from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path

import click

from byoc_cli.cli.errors import EXIT_LOW_CONFIDENCE, handle_errors
from byoc_cli.cli.options import (
    device_option,
    features_option,
    packaged_weights,
    resolve_device,
    seed_option,
    voxel_size_option,
    weights_option,
)

log = logging.getLogger("byoc")

DEPTH_EXTENSIONS = (".png", ".tif", ".tiff")
#: per-feature defaults, chosen by accuracy and time on the 3DMatch sample
#: (`benchmarks/max_points.py`, README "Choosing --max-points")
FEATURE_DEFAULTS = {
    # 5000 of ~20k kept points at 2.5 cm: matching 0.09 s; 10000 costs 3.5x that, all 16x
    "byoc": {"estimator": "procrustes", "num_correspondences": 200, "max_points": 5000},
    # Open3D's tutorial voxel for FPFH; RANSAC needs more than the top 200 of noisy FPFH matches;
    # 10000 keeps every point of a 3DMatch fragment at 5 cm (median rotation error 2.9 deg
    # against 4.8 deg with 5000) and bounds the matching cost of larger scans
    "fpfh": {
        "estimator": "ransac",
        "num_correspondences": 1000,
        "voxel_size": 0.05,
        "max_points": 10000,
    },
}


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

    path = weights or packaged_weights()
    if path is None:
        raise click.UsageError(
            "--features byoc needs --weights PATH (this version ships no trained weights "
            "yet); or use --features fpfh"
        )
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
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, allow_dash=True, path_type=Path),
    default=Path("-"),
    show_default=True,
    help="Where to write T (4 lines of 4 numbers); '-' is stdout.",
)
@click.option(
    "--aligned",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write the source, transformed into the target frame, as binary PLY.",
)
@click.option(
    "--json",
    "json_path",
    type=click.Path(dir_okay=False, allow_dash=True, path_type=Path),
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
    "auto: procrustes for byoc features, ransac for fpfh.",
)
@click.option(
    "--refine",
    type=click.Choice(["none", "icp"]),
    default="none",
    show_default=True,
    help="Refine with point-to-plane ICP (open3d).",
)
@click.option(
    "--max-points",
    type=click.IntRange(min=0),
    default=None,
    help="Seeded random subset of kept points per cloud that enters matching (0 = all) "
    "[default: 5000 with byoc features, 10000 with fpfh].",
)
@click.option(
    "--num-correspondences",
    type=click.IntRange(min=3),
    default=None,
    help="Top-k ratio-test matches kept per direction [default: 200 for byoc, 1000 for fpfh].",
)
@click.option(
    "--min-confidence",
    type=click.FloatRange(0, 1),
    default=0.0,
    show_default=True,
    help="Exit 3 when the confidence is below this.",
)
@click.option(
    "--scale",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Multiply input coordinates by this (0.001 for millimetres); disables the "
    "unit check. T is written in the input units.",
)
@click.option(
    "--intrinsics",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="For depth-image inputs: Open3D intrinsics JSON or a 3x3 text matrix.",
)
@click.option(
    "--depth-scale",
    type=click.FloatRange(min=0, min_open=True),
    default=1000.0,
    show_default=True,
    help="Depth-image units per metre (1000 = mm, 5000 = TUM).",
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
    if str(output) == "-" and json_path is not None and str(json_path) == "-":
        raise click.UsageError("-o and --json cannot both be stdout")
    for path in (source, target):
        if path.suffix.lower() in DEPTH_EXTENSIONS and intrinsics is None:
            raise click.BadParameter(
                f"{path} is a depth image: --intrinsics is required", param_hint="'--intrinsics'"
            )
    defaults = FEATURE_DEFAULTS[features]
    if estimator == "auto":
        estimator = defaults["estimator"]
    if num_correspondences is None:
        num_correspondences = defaults["num_correspondences"]
    if max_points is None:
        max_points = defaults["max_points"]
    from byoc_cli import __version__
    from byoc_cli.geometry import apply_transform
    from byoc_cli.io import atomic_write_text, write_ply, write_transform
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
    result = register_clouds(points_src, points_tgt, extractor, config)
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

    written: list[Path] = []
    try:
        if aligned is not None:
            moved = apply_transform(T, points_src / (scale or 1.0))
            write_ply(aligned, moved.numpy())
            written.append(aligned)
        if json_path is not None:
            text = json.dumps(report, indent=2) + "\n"
            if str(json_path) == "-":
                sys.stdout.write(text)
            else:
                atomic_write_text(json_path, text)
                written.append(json_path)
        write_transform(str(output) if str(output) == "-" else output, T.numpy())
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        raise
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
