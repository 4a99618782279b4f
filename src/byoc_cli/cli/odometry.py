"""``byoc odometry --rgbd-dir SEQ -o traj.txt``: the camera trajectory of an RGB-D video."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.display import print_table
from byoc_cli.cli.errors import CliError, handle_errors
from byoc_cli.cli.options import (
    DEGREES,
    DEPTH_SCALE,
    LENGTH,
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
from byoc_cli.cli.output import (
    claim_outputs,
    is_stdout,
    main_output,
    write_json,
    write_stdout,
)
from byoc_cli.cli.pairwise import StageProgress, pairwise_setup
from byoc_cli.cli.recipe_options import build_recipe, recipe_options
from byoc_cli.pipeline.recipe import RegistrationRecipe

log = logging.getLogger("byoc")


@dataclass(frozen=True)
class OdometryOptions:
    """The options of ``odometry`` besides the sequence, the outputs, ``--eval`` and ``-q``."""

    icp_voxel: float
    max_depth: float
    frame_stride: int
    max_frames: int
    keyframe_rotation: float
    keyframe_translation: float
    min_fitness: float
    pose_graph: bool
    init_poses: Path | None
    intrinsics: Path | None
    depth_scale: float | None
    device: str
    recipe: RegistrationRecipe
    recipe_file: Path | None = None


def _load_sequence(rgbd_dir: Path, intrinsics: Path | None, depth_scale: float | None):
    from byoc_cli.io.rgbd import discover_sequences

    sequences = discover_sequences(rgbd_dir, intrinsics=intrinsics, depth_scale=depth_scale)
    if len(sequences) > 1:
        names = ", ".join(s.name for s in sequences[:3])
        raise CliError(
            f"{rgbd_dir}: holds {len(sequences)} RGB-D sequences ({names}, ...); "
            "pass the folder of one"
        )
    return sequences[0]


def _global_start(extractor, register_config):
    """``T_tgt_src`` of two frames by the pairwise registration of ``byoc register``."""
    import torch

    from byoc_cli.pipeline.register import register_clouds

    def start(points_src, points_tgt):
        result = register_clouds(
            torch.from_numpy(points_src), torch.from_numpy(points_tgt), extractor, register_config
        )
        return result.T_tgt_src.numpy()

    return start


def _given_poses(path: Path, sequence, used: list[int]) -> tuple[list, dict]:
    """The poses of ``--init-poses`` per frame of ``sequence`` (None: none matched) and what
    the report says of them.

    Raises:
        InputError: an unreadable or malformed file, or one that gives no motion between two
            used frames (matched: TUM by timestamp, ``.log`` by frame number).
    """
    from itertools import pairwise

    from byoc_cli.errors import InputError
    from byoc_cli.io.trajectory import read_trajectory
    from byoc_cli.pipeline.motion_prior import STAMP_TOLERANCE, poses_by_id, poses_by_stamp

    given = read_trajectory(path)
    frames = sequence.frames
    if given.format == "log":
        poses = poses_by_id(given.keys, given.poses, [f.index for f in frames])
        how = "the frame's number as the record's first number"
    else:  # the stamps odometry writes: the timestamp, else the frame number
        stamps = [f.index if f.timestamp is None else f.timestamp for f in frames]
        poses = poses_by_stamp(given.keys, given.poses, stamps, STAMP_TOLERANCE)
        how = f"the nearest timestamp within {STAMP_TOLERANCE:g} s"
    matched = sum(poses[f] is not None for f in used)
    if not any(poses[a] is not None and poses[b] is not None for a, b in pairwise(used)):
        raise InputError(
            path, f"gives a pose to {matched} of the {len(used)} frames used, no two in a row "
            f"(frames are matched by {how})"
        )  # fmt: skip
    if matched < len(used):
        log.warning("%s: no pose for %d of %d frames", path, len(used) - matched, len(used))
    report = {"file": str(path), "format": given.format, "matched_by": how}
    return poses, {**report, "frames_matched": matched}


def evaluate(sequence, trajectory) -> dict:
    """ATE and RPE (per second when the frames have timestamps, and per frame) against the
    sequence's poses, over the frames that have one.

    Raises:
        CliError: fewer than 2 used frames have a ground-truth pose.
    """
    import numpy as np

    from byoc_cli.evaluation.trajectory import absolute_trajectory_error, relative_pose_error

    frames = [sequence.frames[f] for f in trajectory.frames]
    with_gt = [n for n, frame in enumerate(frames) if frame.pose is not None]
    if len(with_gt) < 2:
        raise CliError(
            f"{sequence.root}: --eval needs ground-truth poses; {len(with_gt)} of the "
            f"{len(frames)} frames used have one"
        )
    est = trajectory.poses[with_gt]
    gt = np.stack([frames[n].pose for n in with_gt])
    ate = absolute_trajectory_error(est, gt)
    report = {
        "num_frames": len(with_gt),
        "ate_m": {"rmse": ate.rmse, "mean": ate.mean, "median": ate.median, "max": ate.max},
        "rpe": {},
    }
    stamps = [frames[n].timestamp for n in with_gt]
    deltas = [("per_frame", None)]
    if all(s is not None for s in stamps):
        deltas.insert(0, ("per_second", np.asarray(stamps)))
    for name, stamp_array in deltas:
        rpe = relative_pose_error(est, gt, stamp_array, 1.0)
        report["rpe"][name] = {
            "translation_rmse_m": rpe.translation_rmse,
            "rotation_rmse_deg": rpe.rotation_rmse_deg,
            "translation_mean_m": rpe.translation_mean,
            "rotation_mean_deg": rpe.rotation_mean_deg,
            "num_pairs": rpe.num_pairs,
        }
    return report


def _print_eval(report: dict, name: str) -> None:
    ate = report["ate_m"]
    rows = [["ATE RMSE (m)", f"{ate['rmse']:.4f}"], ["ATE median (m)", f"{ate['median']:.4f}"]]
    for key, label in (("per_second", "per second"), ("per_frame", "per frame")):
        if key in report["rpe"]:
            rpe = report["rpe"][key]
            rows.append([f"RPE {label}: translation RMSE (m)", f"{rpe['translation_rmse_m']:.4f}"])
            rows.append([f"RPE {label}: rotation RMSE (deg)", f"{rpe['rotation_rmse_deg']:.3f}"])
    print_table(
        f"trajectory error: {name}",
        ["metric", "value"],
        rows,
        [f"{report['num_frames']} frames with ground truth; TUM RGB-D definitions"],
    )


@click.command(
    "odometry",
    epilog="Exit codes: 0 written; 1 bad input (unreadable frame, --eval without ground "
    "truth) or runtime error; 2 usage error. Lost frames (no start fitted) keep the "
    "constant-velocity prediction and are listed in --json.",
)
@click.option(
    "--rgbd-dir",
    required=True,
    type=click.Path(path_type=Path),
    help="One RGB-D sequence (TUM, 3DMatch/7-Scenes, ScanNet, Redwood layouts); depth is enough.",
)
@apply(
    path_option(
        "-o",
        "--output",
        dash=True,
        default=Path("-"),
        show_default=True,
        help="The trajectory, TUM format (timestamp tx ty tz qx qy qz qw; the frame number "
        "when the layout has no timestamps); '-' is stdout.",
    ),
    path_option(
        "--json",
        "json_path",
        dash=True,
        default=None,
        help="Write a JSON report (stats, timings, --eval figures); '-' is stdout.",
    ),
    click.option(
        "--eval",
        "do_eval",
        is_flag=True,
        help="Compare with the sequence's ground truth: ATE and RPE (TUM) on stderr.",
    ),
    recipe_options(
        "recipe",
        "features",
        "weights",
        "fixed_voxel_size",
        "estimator",
        "max_points",
        "num_correspondences",
    ),
    float_option(
        "--icp-voxel",
        type=VOXEL,
        default=0.025,
        help="Finest voxel of the refinement (the multiscale point-to-plane ICP of byoc "
        "register; its coarser levels scale with it), metres.",
    ),
    float_option("--max-depth", type=LENGTH, default=4.0, help="Drop depth beyond this, metres."),
    int_option("--frame-stride", min=1, default=1, help="Use every N-th frame."),
    int_option("--max-frames", default=0, help="Use at most this many frames (0 = all)."),
    float_option(
        "--keyframe-rotation",
        type=DEGREES,
        default=10.0,
        help="New keyframe past this rotation from the current one, degrees.",
    ),
    float_option(
        "--keyframe-translation",
        type=LENGTH,
        default=0.1,
        help="New keyframe past this translation from the current one, metres.",
    ),
    float_option(
        "--min-fitness",
        type=finite_float(0, 1),
        default=0.6,
        help="ICP is accepted when this share of the frame lies on the keyframe.",
    ),
    click.option(
        "--pose-graph",
        is_flag=True,
        help="Optimise a pose graph over the keyframes with loop edges (slower).",
    ),
    path_option(
        "--init-poses",
        help="A trajectory of the same frames (wheel odometry, an IMU, an earlier run): TUM "
        "(frames matched by the nearest timestamp within 0.02 s; the frame number when the "
        "layout has none) or .log (by frame number). Each frame's ICP starts from the "
        "previous frame's pose times its motion; the constant velocity where that does not "
        "fit or a pose is missing.",
    ),
    path_option("--intrinsics", help="Intrinsics file for a sequence that ships none."),
    float_option(
        "--depth-scale", type=DEPTH_SCALE, help="Depth units per metre [default: the layout's]."
    ),
    recipe_options("seed"),
    device_option,
    verbose_option,
    quiet_option("No progress bar; only errors on stderr.", expose_value=True),
)
@handle_errors
def odometry(
    rgbd_dir: Path,
    output: Path,
    json_path: Path | None,
    do_eval: bool,
    quiet: bool,
    **options: Any,
) -> None:
    """Track the depth camera of one RGB-D sequence and write its trajectory (TUM format).

    Each frame is registered onto the current keyframe by coarse-to-fine point-to-plane ICP
    from the motion of --init-poses when given, else (or when that does not fit) from the
    constant-velocity prediction (else the previous pose, else a global start with
    --features); a new keyframe starts when the motion exceeds --keyframe-rotation or
    --keyframe-translation. The first frame is the world.
    """
    from byoc_cli.io.trajectory import format_tum_trajectory
    from byoc_cli.pipeline.odometry import (
        OdometryConfig,
        config_dict,
        estimate_trajectory,
        used_frames,
    )

    started = time.perf_counter()
    options["device"] = resolve_device(options["device"])
    recipe_file = options.get("recipe_path")
    recipe = build_recipe(options)
    if recipe.features.voxel == "auto":  # depth frames are in metres: the features' own voxel
        recipe = recipe.changed(features__voxel="own")
    o = OdometryOptions(**options, recipe=recipe, recipe_file=recipe_file)
    output = main_output(output, json_path)
    weights = None if recipe.features.weights is None else Path(recipe.features.weights)
    outputs = claim_outputs(
        {"-o": output, "--json": json_path},
        inputs=(o.intrinsics, weights, recipe_file, o.init_poses),
        input_dirs=(rgbd_dir,),
    )
    extractor, register_config, weights_info = pairwise_setup(recipe, o.device)
    sequence = _load_sequence(rgbd_dir, o.intrinsics, o.depth_scale)
    config = OdometryConfig(
        voxel_size=o.icp_voxel,
        max_depth=o.max_depth,
        frame_stride=o.frame_stride,
        max_frames=o.max_frames,
        min_fitness=o.min_fitness,
        keyframe_rotation_deg=o.keyframe_rotation,
        keyframe_translation=o.keyframe_translation,
        pose_graph=o.pose_graph,
        seed=recipe.seed,
    )
    given, init_report = None, None
    if o.init_poses is not None:
        used = used_frames(len(sequence.frames), config)
        given, init_report = _given_poses(o.init_poses, sequence, used)
    progress = StageProgress(quiet)
    try:
        trajectory = estimate_trajectory(
            sequence,
            config,
            _global_start(extractor, register_config),
            lambda done, total: progress("frames", done, total),
            given,
        )
    finally:
        progress.close()
    frames = [sequence.frames[f] for f in trajectory.frames]
    stamps = [f.timestamp if f.timestamp is not None else f.index for f in frames]
    text = format_tum_trajectory(stamps, trajectory.poses)
    evaluation = evaluate(sequence, trajectory) if do_eval else None
    seconds = time.perf_counter() - started
    report = {
        "command": "byoc odometry",
        "sequence": str(sequence.root),
        "layout": sequence.layout,
        "num_frames": len(trajectory.frames),
        "num_keyframes": len(trajectory.keyframes),
        "lost_frames": [frames[n].index for n in trajectory.lost],
        "stats": trajectory.stats,
        "settings": {**config_dict(config), "features": extractor.name},
        "init_poses": init_report,
        "recipe": recipe.as_dict(),
        "weights": weights_info,
        "evaluation": evaluation,
        "timings_s": {**trajectory.timings, "command": seconds},
        "frames_per_second": len(trajectory.frames) / seconds,
    }
    with outputs:  # every file is committed at the end of the block, or none
        write_json(json_path, report)
        if is_stdout(output):
            write_stdout(text)
        elif output is not None:
            from byoc_cli.io import atomic_write_text

            atomic_write_text(output, text)
    if trajectory.lost:
        log.warning("%d frame(s) lost (constant-velocity pose kept)", len(trajectory.lost))
    log.info("%d frames, %d keyframes, %.1f s", len(frames), len(trajectory.keyframes), seconds)
    if evaluation is not None:
        _print_eval(evaluation, sequence.name)
