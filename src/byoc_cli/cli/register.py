"""``byoc register SOURCE TARGET``: write the transform that maps SOURCE into TARGET's frame."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.display import is_quiet
from byoc_cli.cli.errors import EXIT_LOW_CONFIDENCE, handle_errors
from byoc_cli.cli.options import (
    device_option,
    path_option,
    resolve_device,
    verbosity_options,
)
from byoc_cli.cli.output import (
    check_binary_stdout,
    claim_outputs,
    is_stdout,
    main_output,
    write_json,
    write_stdout,
)
from byoc_cli.cli.pair_files import (
    check_pair_files,
    qc_name,
    qc_option,
    write_aligned_source,
    write_pair_qc,
)
from byoc_cli.cli.pairwise import (
    ambiguity,
    check_ambiguity,
    check_depth_inputs,
    cloud_factors,
    format_length,
    init_options,
    init_settings,
    input_options,
    register_pair,
    registrar,
    registration_report,
    seen_through,
    turned_rival,
)
from byoc_cli.cli.recipe_options import PAIRWISE, build_recipe, recipe_options

log = logging.getLogger("byoc")


@dataclass(frozen=True)
class RegisterOptions:
    """The options of ``register`` besides the clouds, the outputs and the recipe's."""

    scale: float | None
    source_scale: float | None
    target_scale: float | None
    intrinsics: Path | None
    depth_scale: float | None
    device: str
    init_path: Path | None = None
    max_correction: tuple[float, float | None] | None = None
    init_mode: str | None = None


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
    help="Write the source, transformed into the target frame: binary PLY ('-' is stdout, "
    "with -o FILE), or by extension .las/.laz (a LAS/LAZ source's header and point records "
    "with new x, y, z) or .e57 (one scan).",
)
@path_option(
    "--json",
    "json_path",
    dash=True,
    default=None,
    help="Write a JSON report ('-' is stdout, then T goes only to -o).",
)
@path_option(
    "--init",
    "init_path",
    default=None,
    dash=True,
    help="An initial pose: a guess of T (4 lines of 4 numbers, the convention of -o; '-' "
    "reads it from stdin) from odometry, a robot, GNSS/IMU or an earlier result. The "
    "registration refines from it (no features) and exits 3 when it leaves --max-correction "
    "or fits poorly (docs/poses.md).",
)
@init_options
@qc_option
@recipe_options(*PAIRWISE)
@input_options
@device_option
@verbosity_options
@handle_errors
def register(
    source: Path,
    target: Path,
    output: Path,
    aligned: Path | None,
    json_path: Path | None,
    qc_dir: Path | None,
    **options: Any,
) -> None:
    """Register SOURCE onto TARGET and write T, the 4x4 transform that maps SOURCE into
    TARGET's frame: x_tgt = R x_src + t (column vectors; T = [[R, t], [0, 0, 0, 1]]).

    SOURCE and TARGET are point clouds (.ply, .pcd, .xyz, .pts, .npy of shape N x 3,
    .las, .laz, .e57; one scan of a multi-scan E57 file as FILE.e57:K, 0-based) in any unit
    (the voxel follows their size; T is in their coordinates as read; --scale brings them to
    metres), or depth images (.png, with --intrinsics and --depth-scale). Lengths the report
    gives are in metres when the unit is known, else in input units.
    """
    started = time.perf_counter()
    recipe_file = options.get("recipe_path")
    recipe = build_recipe(options)
    o = RegisterOptions(**{**options, "device": resolve_device(options["device"])})
    output = main_output(output, json_path)
    check_depth_inputs((source, target), o.intrinsics)
    check_binary_stdout(aligned, "--aligned")
    init_settings(o.init_path, options)  # usage errors first
    inputs = (source, target, o.intrinsics, recipe_file, _path(recipe.features.weights))
    check_pair_files(aligned, source, qc_dir)
    outputs = claim_outputs(
        {"-o": output, "--aligned": aligned, "--json": json_path}, inputs=(*inputs, o.init_path)
    )
    from byoc_cli.io import atomic_write_text, format_transform, read_transform

    guess = init_settings(None if o.init_path is None else read_transform(o.init_path), options)
    made = registrar(recipe, o.device)
    factors, factors_given = cloud_factors(options)
    load = {"intrinsics": o.intrinsics, "depth_scale": o.depth_scale}
    result = register_pair(made, source, target, factors, load, guess)
    min_confidence = recipe.gate.min_confidence
    run = {
        "min_confidence": min_confidence,
        "scale": o.scale,
        "factors": factors,
        "factors_given": factors_given,
        "depth_scale": o.depth_scale,
        "device": o.device,
        "started": started,
        "init_file": o.init_path,
    }
    report = registration_report(result, made, (source, target), run)
    T = result.T_tgt_src

    with outputs:  # every file is committed at the end of the block, or none
        if aligned is not None:
            write_aligned_source(aligned, source, T, factors, load)
        if qc_dir is not None:
            report["qc"] = write_pair_qc(outputs, qc_dir, qc_name(source, target), report, load)
        write_json(json_path, report)
        if is_stdout(output):
            write_stdout(format_transform(T))
        elif output is not None:
            atomic_write_text(output, format_transform(T))
    quiet = is_quiet(False)  # -q: errors and the result (T, the exit code) only
    if not quiet:
        seconds = report["timings_s"]["command"]
        click.echo(summary_line(source, target, result, seconds, report["unit"]), err=True)
    if not result.passed and not quiet:
        click.echo(failure_line(result, min_confidence, report["unit"]), err=True)
    if not result.passed:
        raise SystemExit(EXIT_LOW_CONFIDENCE)


def summary_line(source: Path, target: Path, result, seconds: float, unit: str | None) -> str:
    """The line a successful ``byoc register`` prints on stderr: confidence, inliers, the
    voxel used (in metres when ``unit`` is ``"m"``, else in input units) and the time (``-q``
    silences it); from an initial pose, the path, the correction and the trust region."""
    voxel = f"{result.voxel_size:g} m" if unit == "m" else f"{result.voxel_size:.4g} input units"
    if result.path == "local":
        return (
            f"byoc: registered {source} -> {target} from --init (local): confidence "
            f"{result.confidence:.3f}, correction {_moved(result.init['correction'], unit)} "
            f"(--max-correction {_moved(result.init['trust_region'], unit)}), fitness "
            f"{result.inlier_ratio:.2f}, voxel {voxel}, {seconds:.1f} s"
        )
    line = (
        f"byoc: registered {source} -> {target}: confidence {result.confidence:.3f}, "
        f"{result.num_inliers}/{result.num_correspondences} inliers within "
        f"{format_length(result.inlier_threshold, unit)}, voxel {voxel}, {seconds:.1f} s"
    )
    fallback = result.fallback
    if fallback and fallback["used"] and fallback["features"] == "fpfh":
        line += (
            f" (FPFH features: the learned ones reached confidence "
            f"{fallback['learned_confidence']:.3f}{_reproduced(result.reproduced)})"
        )
    elif result.features_choice and result.features_choice["first"] == "fpfh":
        why = _why_fpfh(result.features_choice)
        if result.features == "fpfh":
            line += f" (FPFH features: {why}{_coarser(result.features_choice)}"
            line += f"{_reproduced(result.reproduced)})"
        else:  # the learned features' second opinion was kept
            first = fallback["first_confidence"] or 0.0
            line += f" ({why}; FPFH reached confidence {first:.3f})"
    retried = result.retries
    if retried and retried["kept_seed"] is not None and not (fallback and fallback["used"]):
        line += (
            f" (retry with seed {retried['kept_seed']}: the first try reached confidence "
            f"{retried['first_confidence']:.3f})"
        )
    if result.init is not None:
        line += f" (global; {_moved(result.init['correction'], unit)} from --init)"
    return line


def _why_fpfh(choice: dict) -> str:
    """Why FPFH went first (the report's ``features_choice``), for :func:`summary_line`:
    smooth surfaces, with the clouds' rough shares, or an object below the trained size
    (whose shares are not measured)."""
    shares = choice["rough_share"]
    if choice.get("small_object") and not shares:
        unit = ", read as millimetres" if choice.get("in_millimetres") else ""
        return f"an object below the trained size{unit}"
    rough = " and ".join(f"{100 * r:.0f} %" for r in shares)
    if choice.get("small_object") and max(shares) > choice["smooth_share"]:
        return f"an object below the trained size, {rough} rough"
    return f"smooth surfaces, {rough} rough"


def _coarser(choice: dict) -> str:
    """What the retry with coarser FPFH features of an object said when its result was kept
    (the report's ``features_choice.coarser``), for :func:`summary_line`."""
    note = choice.get("coarser")
    if not note or note["used"] is None:
        return ""
    return (
        f"; features at {note['used']:g}x the voxel, the first try reached confidence "
        f"{note['first_confidence']:.3f}"
    )


def _reproduced(note: dict | None) -> str:
    """What the repeats of an FPFH result said (a smooth pair's, or the fallback's of an
    object), for :func:`summary_line`."""
    if note is None:
        return ""
    if note["agree"]:
        return (
            f"; reproduced by {len(note['repeats'])} repeats, confidence "
            f"{note['model_confidence']:.3f} before"
        )
    return f"; not reproduced by its {len(note['repeats'])} repeats"


def failure_line(result, min_confidence: float, unit: str | None) -> str:
    """The line ``byoc register`` prints on stderr when it exits 3: why T is likely wrong."""
    init = result.init or {}
    written = "T is likely wrong (written all the same)"
    if (result.turns or {}).get("ambiguous"):
        return f"byoc: {ambiguity(result.turns)}: {written}"
    if (result.check or {}).get("ambiguous"):
        return f"byoc: {check_ambiguity(result.check, unit)}: {written}"
    if not (result.visibility or {}).get("consistent", True):
        return f"byoc: {seen_through(result.visibility)}: {written}"
    turned = turned_rival(result.cues)
    if turned is not None:
        return f"byoc: {turned}: {written}"
    if init.get("check") == "disagrees":
        return (
            f"byoc: the global result lies {_moved(init['correction'], unit)} from --init, "
            f"beyond --max-correction {_moved(init['trust_region'], unit)}, and the local "
            f"registration from --init did not pass (confidence "
            f"{init['local']['confidence']:.3f}): {written}"
        )
    if result.path == "local" and not init["inside_trust_region"]:
        return (
            f"byoc: the result moved {_moved(init['correction'], unit)} from --init, beyond "
            f"--max-correction {_moved(init['trust_region'], unit)}: {written}"
        )
    return (
        f"byoc: confidence {result.confidence:.3f} is below --min-confidence "
        f"{min_confidence:g}: {written}"
    )


def _moved(correction: dict, unit: str | None) -> str:
    """``12.3 deg / 45.6 cm`` of a correction or trust region (its translation in ``unit``)."""
    return (
        f"{correction['rotation_deg']:.1f} deg / {format_length(correction['translation'], unit)}"
    )


def _path(name: str | None) -> Path | None:
    return None if name is None else Path(name)
