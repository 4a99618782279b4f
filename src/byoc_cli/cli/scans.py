"""``byoc register-scans SCANS... --out DIR``: many overlapping scans into one frame."""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.display import is_quiet
from byoc_cli.cli.errors import EXIT_LOW_CONFIDENCE, handle_errors
from byoc_cli.cli.options import (
    SCALE,
    VOXEL,
    apply,
    device_option,
    finite_float,
    float_option,
    int_option,
    path_option,
    quiet_option,
    resolve_device,
    verbose_option,
)
from byoc_cli.cli.output import claim_outputs, write_json, write_stdout
from byoc_cli.cli.pairwise import StageProgress, pairwise_setup
from byoc_cli.cli.recipe_options import build_recipe, recipe_options
from byoc_cli.cli.scans_init import (
    ScansInit,
    about,
    about_first,
    announce,
    init_poses_options,
    pair_init_json,
    resolve_init,
    unscaled,
)
from byoc_cli.io.cloudpath import cloud_stem
from byoc_cli.pipeline.recipe import RegistrationRecipe

log = logging.getLogger("byoc")

#: what report.json says it is (a folder holding it is this command's own)
REPORT_COMMAND = "byoc register-scans"
#: the marker (``.byoc-register-scans``) that makes a folder this command's own from the start
MARKER = "register-scans"


@dataclass(frozen=True)
class ScansOptions:
    """The options of ``register-scans`` besides the scans, the folder and ``-q``."""

    merged: Path | None
    merged_voxel: float
    icp_voxel: float
    min_fitness: float
    all_pairs_max: int
    neighbours: int
    scale: float | None
    device: str
    recipe: RegistrationRecipe
    init_poses: str | None = None
    max_correction: tuple | None = None
    recipe_file: Path | None = None


def _is_scans_folder(folder: Path) -> bool:
    """A folder this command wrote (its report), or created (its marker: a run killed
    before it wrote the report)."""
    from byoc_cli.errors import InputError
    from byoc_cli.io.folders import is_marked
    from byoc_cli.io.inputs import read_json_input

    if is_marked(folder, MARKER):
        return True
    try:
        report = read_json_input(folder / "report.json")
    except InputError:
        return False
    return isinstance(report, dict) and report.get("command") == REPORT_COMMAND


def _load(path: Path, scale: float | None):
    """One scan as ``(N, 3)`` float64 metres."""
    from byoc_cli.io import check_units, read_point_cloud

    loaded = read_point_cloud(path)
    if loaded.num_nonfinite_dropped:
        log.warning(
            "%s: dropped %d point(s) with NaN/Inf coordinates", path, loaded.num_nonfinite_dropped
        )
    if scale is None:
        check_units(loaded.points, path)
        return loaded.points
    return loaded.points * scale


@contextlib.contextmanager
def _results_folder(out: Path):
    """Create ``out`` and ``out/poses`` and mark ``out`` as this command's own before anything
    runs, so that a killed run leaves a folder the same command accepts; remove the stale
    temporaries of a killed run. When the block fails, a folder that was new or empty is
    left as it was (marker and folders removed)."""
    from byoc_cli.io.folders import mark_folder, new_folders, remove_stale_temporaries

    was_empty = not out.exists() or not any(out.iterdir())
    with new_folders(out):
        marker = mark_folder(out, MARKER)  # before anything else: an empty folder is ours too
        try:
            with new_folders(out / "poses"):
                for folder in (out, out / "poses"):
                    remove_stale_temporaries(folder)
                yield
        except BaseException:
            if was_empty:
                marker.unlink(missing_ok=True)
            raise


def _stale_poses(poses_dir: Path, written: list[Path]) -> list[Path]:
    """The pose files of an earlier run in ``poses_dir`` that this run does not write (a scan
    no longer given, or no longer placed): poses/ holds exactly the last run's poses."""
    keep = {path.name for path in written}
    return sorted(
        p
        for p in poses_dir.glob("*.txt")
        if p.name not in keep and p.is_file() and not p.is_symlink()
    )


def _pair_json(pair, poses, scans: list[Path], origin, unit: float) -> dict:
    import numpy as np

    from byoc_cli.pipeline.posegraph import transform_difference

    record = {
        "i": pair.i,
        "j": pair.j,
        "target": str(scans[pair.i]),
        "source": str(scans[pair.j]),
        "kind": pair.kind,
        "status": pair.status,
        "confidence": pair.confidence,
        "fitness": pair.fitness,
        "rmse_m": pair.rmse,
        "edge": pair.edge or None,
        "pruned": pair.pruned,
        "seconds": pair.seconds,
        "error": pair.error or None,
        "T_i_j": None if pair.T_i_j is None else unscaled(about(pair.T_i_j, origin), unit).tolist(),
    }
    if pair.init is not None:
        record["init"] = pair_init_json(pair.init, unit)
    if pair.T_i_j is not None and poses[pair.i] is not None and poses[pair.j] is not None:
        graph = np.linalg.inv(poses[pair.i]) @ poses[pair.j]
        rot, trans = transform_difference(graph, pair.T_i_j)  # in the scans' scaled units
        record["disagreement_with_poses"] = {"rotation_deg": rot, "translation_m": trans * unit}
    return record


@click.command(
    "register-scans",
    epilog="Writes DIR/poses/<scan-stem>.txt (T_world_scan, the first scan is the world), "
    "DIR/trajectory.log (3DMatch/Open3D .log) and DIR/report.json; --merged a PLY. Exit "
    "codes: 0 every scan placed; 1 bad input or runtime error (nothing written); 2 usage "
    "error; 3 some scans overlap no placed scan (the others are written, the report lists "
    "them).",
)
@click.argument("scans", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--out",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Results folder (new, empty, or one this command wrote).",
)
@apply(
    path_option("--merged", default=None, help="Write the merged model here (binary PLY)."),
    float_option(
        "--merged-voxel", type=VOXEL, default=0.01, help="Voxel size of the merged model, metres."
    ),
    recipe_options("recipe", "features", "weights"),
    float_option(
        "--voxel-size",
        type=VOXEL,
        default=None,
        help="Feature voxel in metres [default: from the scans: at the size of rooms and "
        "desks the features' own; scans of another size (objects, LiDAR, millimetres) are "
        "scaled to it, the report says by how much, and poses and the merged model are "
        "written in the input units].",
    ),
    recipe_options("estimator", "max_points", "num_correspondences"),
    float_option(
        "--icp-voxel",
        type=VOXEL,
        default=0.02,
        help="Finest voxel of the refinement (the multiscale point-to-plane ICP of byoc "
        "register; its coarser levels scale with it), metres.",
    ),
    float_option(
        "--min-fitness",
        type=finite_float(0, 1),
        default=0.3,
        help="A pair enters the pose graph when this share of its source lies on the target "
        "after ICP.",
    ),
    int_option(
        "--all-pairs-max",
        min=2,
        default=20,
        help="Up to this many scans every pair is tried; above, neighbours in the given order "
        "plus candidate pairs that overlap under a first pose graph.",
    ),
    int_option(
        "--neighbours",
        min=1,
        default=2,
        help="Large sets: each scan is paired with the next N scans.",
    ),
    float_option(
        "--scale",
        type=SCALE,
        help="Multiply input coordinates by this (0.001 for millimetres); disables the unit "
        "check. Poses and the merged model are written in the input units.",
    ),
    init_poses_options,
    recipe_options("seed"),
    device_option,
    verbose_option,
    quiet_option("No progress bars; only errors on stderr.", expose_value=True),
)
@handle_errors
def register_scans(scans: tuple[Path, ...], out: Path, quiet: bool, **options: Any) -> None:
    """Register overlapping SCANS (point clouds) into the frame of the first one.

    An E57 file of several scans gives each of its scans (in the file's frame: their stored
    poses applied), named FILE.e57:K (0-based) and poses/<stem>_scanK.txt; they start from
    their stored poses unless --init-poses says otherwise.

    Every overlapping pair is registered with the pairwise registration of `byoc register`
    (the same --features, --weights, --voxel-size) and refined by ICP; a pose graph of the
    pairs, with their information matrices, is optimised with Open3D's global optimisation,
    which prunes wrong pairs. A one-line summary goes to stdout. With --init-poses, the pairs
    that overlap under the poses are refined from them instead (no features), within
    --max-correction, and the graph starts at the poses.
    """
    started = time.perf_counter()
    options["device"] = resolve_device(options["device"])
    recipe_file = options.get("recipe_path")
    recipe = build_recipe(options)
    settings = ScansOptions(**options, recipe=recipe, recipe_file=recipe_file)
    from byoc_cli.io.e57 import expand_scans

    scans_list = expand_scans(list(scans))  # an E57 file of several scans: each scan
    if len(scans_list) < 2:
        raise click.UsageError("register-scans needs at least 2 scans")
    stems: dict[str, Path] = {}
    for path in scans_list:
        stem = cloud_stem(path)
        if stem in stems:
            raise click.BadParameter(
                f"{stems[stem]} and {path} have the same name {stem!r} "
                "(poses/<name>.txt); rename one",
                param_hint="'SCANS'",
            )
        stems[stem] = path
    init = resolve_init(scans_list, settings.init_poses, settings.max_correction)
    from byoc_cli.io.folders import check_run_folder

    check_run_folder(out, _is_scans_folder, what="register-scans folder")
    announce(init, quiet)
    with _results_folder(out):
        unplaced = _run(scans_list, out, settings, quiet, started, init)
    if unplaced:
        names = ", ".join(str(scans_list[k]) for k in unplaced[:5])
        if not is_quiet(quiet):
            click.echo(f"byoc: {len(unplaced)} scan(s) not placed: {names}", err=True)
        raise SystemExit(EXIT_LOW_CONFIDENCE)


def _run(
    scans: list[Path],
    out: Path,
    options: ScansOptions,
    quiet: bool,
    started: float,
    init: ScansInit | None,
) -> list[int]:
    """Register and write everything; returns the indices of the scans not placed."""
    from byoc_cli import __version__
    from byoc_cli.cli.scans_init import register
    from byoc_cli.io import atomic_write_text, format_transform, write_ply
    from byoc_cli.io.trajectory import format_trajectory_log
    from byoc_cli.pipeline.scans import ScansConfig, config_dict, merge_clouds

    pose_paths = [out / "poses" / f"{cloud_stem(path)}.txt" for path in scans]
    outputs = claim_outputs(
        {
            "report": out / "report.json",
            "trajectory": out / "trajectory.log",
            "--merged": options.merged,
            **{f"pose {k}": p for k, p in enumerate(pose_paths)},
        },
        inputs=(
            *scans,
            _path(options.recipe.features.weights),
            options.recipe_file,
            init.path if init is not None and init.source == "file" else None,
        ),
    )
    extractor, register_config, weights_info = pairwise_setup(options.recipe, options.device)
    t0 = time.perf_counter()
    scale = options.scale
    auto = options.recipe.features.voxel == "auto" and scale is None
    points = [_load(path, 1.0 if auto else scale) for path in scans]
    origin, points = about_first(points)  # georeferenced scans: about the first one's middle
    voxel_choice = None
    if auto:  # the scans' own size: brought to the features' scale when it is another
        scale, voxel_choice = _auto_scale(points, scans, extractor.voxel_size)
        if scale is not None:
            points = [p * scale for p in points]
            origin = origin * scale
    load_time = time.perf_counter() - t0
    config = ScansConfig(
        all_pairs_max=options.all_pairs_max,
        neighbours=options.neighbours,
        icp_voxel=options.icp_voxel,
        min_fitness=options.min_fitness,
    )
    progress = StageProgress(quiet)
    extra: dict = {}
    try:
        setup = (extractor, register_config, config, progress, origin)
        labels = [str(p) for p in scans]
        result = register(points, labels, setup, init, scale or 1.0, extra.__setitem__)
    finally:
        progress.close()
    unit = 1.0 / (scale or 1.0)
    poses = [None if T is None else unscaled(about(T, origin), unit) for T in result.poses]
    placed = [k for k, T in enumerate(poses) if T is not None]
    kept = [p for p in result.pairs if p.status == "kept"]
    pruned = [p for p in result.pairs if p.pruned]
    report = {
        "command": REPORT_COMMAND,
        "byoc_cli_version": __version__,
        "convention": "poses/<scan>.txt is T_world_scan (x_world = R x_scan + t); world = "
        "the first scan",
        "scans": [
            {
                "path": str(p),
                "pose": str(pose_paths[k]) if poses[k] is not None else None,
                "num_points": len(points[k]),
                "placed": poses[k] is not None,
            }
            for k, p in enumerate(scans)
        ],
        "num_scans": len(scans),
        "num_placed": len(placed),
        "unplaced": [str(scans[k]) for k in result.unplaced],
        "pairs_tried": len(result.pairs),
        "pairs_kept": len(kept),
        "pairs_failed": sum(p.status == "failed" for p in result.pairs),
        "edges_pruned": len(pruned),
        "pairs": [_pair_json(p, result.poses, scans, origin, unit) for p in result.pairs],
        "settings": {
            "features": extractor.name,
            "voxel_size_m": extractor.voxel_size,
            "estimator": register_config.estimator,
            "num_correspondences": register_config.num_correspondences,
            "max_points": register_config.max_points,
            "seed": options.recipe.seed,
            "scale": scale,
            "voxel_choice": None if voxel_choice is None else voxel_choice.as_dict(),
            "merged_voxel_m": options.merged_voxel if options.merged is not None else None,
            **config_dict(config),
        },
        "recipe": options.recipe.as_dict(),
        "weights": weights_info,
        **extra,
        "timings_s": {"load": load_time, **result.timings},
        "pairs_per_s": len(result.pairs) / max(result.timings["pairs"], 1e-9),
    }
    merged_points = None
    if options.merged is not None:
        t0 = time.perf_counter()
        merged_points = (
            merge_clouds(points, result.poses, options.merged_voxel * (scale or 1.0)) + origin
        ) * unit
        report["timings_s"]["merge"] = time.perf_counter() - t0
    report["timings_s"]["command"] = time.perf_counter() - started

    for path in _stale_poses(out / "poses", [pose_paths[k] for k in placed]):
        outputs.remove(path)
    with outputs:  # every file is committed at the end of the block, or none
        for k in placed:
            atomic_write_text(pose_paths[k], format_transform(poses[k]))
        atomic_write_text(
            out / "trajectory.log", format_trajectory_log([poses[k] for k in placed], placed)
        )
        if merged_points is not None:
            write_ply(options.merged, merged_points)
        write_json(out / "report.json", report)
        write_stdout(
            f"{out}: {len(placed)}/{len(scans)} scans placed, {len(kept)}/{len(result.pairs)} "
            f"pairs kept, {len(pruned)} edges pruned, {time.perf_counter() - started:.1f} s\n"
        )
    return list(result.unplaced)


def _auto_scale(points: list, scans: tuple[Path, ...], reference: float):
    """``(scale or None, VoxelChoice)``: the factor that brings ``points`` (the scans, each
    ``(N, 3)``) to the size the features were made for
    (:func:`byoc_cli.pipeline.scale.trained_scale`; None: they are that size).

    Raises:
        RegistrationError: a scan too small to read a scale from, no extent, points that fill
            a volume, or scans too different in size to be in the same units.
    """
    import torch

    from byoc_cli.pipeline.scale import choose_voxel, measure, trained_scale

    sizes = tuple(
        measure(torch.from_numpy(p), str(path)) for p, path in zip(points, scans, strict=True)
    )
    choice = choose_voxel(sizes, reference)
    return trained_scale(choice), choice


def _path(name: str | None) -> Path | None:
    return None if name is None else Path(name)
