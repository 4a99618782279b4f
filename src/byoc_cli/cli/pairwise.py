"""What the commands that register pairs share: the registrar of a recipe, the pipeline's
settings of a recipe, the check of depth-image inputs, the JSON report of one registration
and progress bars per stage.

``register``, ``register-batch``, ``features``, ``register-scans`` and ``odometry`` build on
this module, so that no command module imports another.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.display import is_quiet, progress_bar
from byoc_cli.cli.options import (
    DEGREES,
    DEPTH_SCALE,
    LENGTH,
    SCALE,
    apply,
    choice_option,
    float_option,
    path_option,
)

log = logging.getLogger("byoc")


#: inputs read as depth images (byoc_cli.pipeline.inputs.DEPTH_EXTENSIONS, without importing numpy)
DEPTH_EXTENSIONS = (".png", ".tif", ".tiff")


#: the options of one registration besides the recipe's (``register`` and ``register-batch``)
input_options = apply(
    float_option(
        "--scale",
        type=SCALE,
        help="Multiply input coordinates by this (0.001 for millimetres); disables the "
        "unit check. T is written in the input units.",
    ),
    float_option(
        "--source-scale",
        type=SCALE,
        help="The source's own factor to metres, for clouds in different units "
        "[default: --scale, else 1 when --target-scale is given]. T maps the source, brought "
        "into the target's units, into the target's frame, in the target's units.",
    ),
    float_option(
        "--target-scale",
        type=SCALE,
        help="The target's own factor to metres [default: --scale, else 1 when --source-scale "
        "is given].",
    ),
    path_option(
        "--intrinsics",
        help="For depth-image inputs: Open3D intrinsics JSON or a 3x3 text matrix.",
    ),
    float_option(
        "--depth-scale",
        type=DEPTH_SCALE,
        default=None,
        help="Depth-image units per metre (1000 = mm, 5000 = TUM) [default: the convention of "
        "the dataset layout around the file (TUM: depth.txt beside depth/, 5000; 3DMatch, "
        "ScanNet, Redwood: 1000), else 1000]. A median depth outside 0.1-20 m is refused.",
    ),
)


#: the defaults of ``--max-correction`` (byoc_cli.pipeline.local, without importing numpy)
MAX_CORRECTION_DEG, MAX_CORRECTION_VOXELS = 20.0, 20.0


class MaxCorrection(click.ParamType):
    """``DEG`` or ``DEG,DIST``: the trust region of a registration from an initial pose
    (``DIST`` in the input's units; without it, the default)."""

    name = "DEG[,DIST]"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None):
        if isinstance(value, tuple):
            return value
        parts = str(value).split(",")
        if len(parts) not in (1, 2) or not parts[0].strip():
            self.fail(f"{value!r} is not DEG or DEG,DIST (for example 20,0.5).", param, ctx)
        degrees = DEGREES.convert(parts[0].strip(), param, ctx)
        distance = LENGTH.convert(parts[1].strip(), param, ctx) if len(parts) == 2 else None
        return degrees, distance


#: how a registration uses an initial pose (``register --init``, ``register-batch``'s init
#: column)
init_options = apply(
    click.option(
        "--max-correction",
        type=MaxCorrection(),
        default=None,
        help="With an initial pose: how far the result may move from it, the rotation in "
        "degrees and the distance the source's centroid moves, in the input's units; beyond "
        f"it the registration exits 3 [default: {MAX_CORRECTION_DEG:g} deg and "
        f"{MAX_CORRECTION_VOXELS:g} refinement voxels, 0.5 m at depth-camera scale].",
    ),
    choice_option(
        "--init-mode",
        choices=["local", "global"],
        default=None,
        help="With an initial pose: 'local' refines from it (no features) [default]; "
        "'global' registers without it, then keeps that result when it lies inside "
        "--max-correction of the pose and passes the gate, else the local result from the "
        "pose when that passes, else exits 3 (docs/poses.md).",
    ),
)


def init_settings(T_init, options: dict) -> dict:
    """The keywords of :meth:`~byoc_cli.pipeline.registrar.Registrar.register` for the initial
    pose ``T_init (4, 4)`` (None: none) and the ``max_correction`` and ``init_mode`` options.

    Raises:
        click.UsageError: ``--max-correction`` or ``--init-mode`` without an initial pose.
    """
    mode, trust = options.get("init_mode"), options.get("max_correction")
    if T_init is None:
        if mode is not None or trust is not None:
            raise click.UsageError("--max-correction and --init-mode go with --init")
        return {}
    return {"init": T_init, "max_correction": trust, "init_mode": mode or "local"}


def cloud_factors(options: dict) -> tuple[tuple[float | None, float | None], bool]:
    """Each cloud's factor to metres from a command's ``scale``, ``source_scale`` and
    ``target_scale`` options: ``((source, target), both given)``. A per-cloud option wins over
    ``--scale``; a cloud with no factor while the other has its own is taken as it is (1);
    ``(None, None)``: no option given."""
    scale = options.get("scale")
    src = scale if options.get("source_scale") is None else options["source_scale"]
    tgt = scale if options.get("target_scale") is None else options["target_scale"]
    if src is None and tgt is None:
        return (None, None), False
    both = src is not None and tgt is not None
    return ((1.0 if src is None else src), (1.0 if tgt is None else tgt)), both


def register_pair(made, source, target, factors: tuple, load: dict, guess: dict | None = None):
    """Register ``source`` onto ``target`` with ``made`` (a
    :class:`~byoc_cli.pipeline.registrar.Registrar`) and each cloud's factor to metres
    (:func:`cloud_factors`); ``load``: ``intrinsics`` and ``depth_scale``; ``guess``: the
    initial pose's keywords (:func:`init_settings`).

    With one factor for both, the registrar reads the files (``scale``). With two, the source
    is read into the target's units (its factor over the target's) and both go to the
    registrar as arrays at the target's factor: ``T`` stays rigid and is in the target's units.
    """
    from byoc_cli.pipeline.inputs import load_cloud

    src, tgt = factors
    guess = guess or {}
    if src == tgt:
        return made.register(source, target, scale=src, **load, **guess)
    points_src = load_cloud(source, scale=src / tgt, **load)
    points_tgt = load_cloud(target, scale=1.0, **load)
    return made.register(points_src, points_tgt, scale=tgt, **load, **guess)


def registrar(recipe, device: str):
    """The :class:`~byoc_cli.pipeline.registrar.Registrar` of a command's recipe.

    Raises:
        click.UsageError: byoc features, no weights file and no shipped weights.
    """
    from byoc_cli.pipeline.default_weights import default_weights_path
    from byoc_cli.pipeline.registrar import Registrar

    features, weights = recipe.features.kind, recipe.features.weights
    if features == "fpfh" and weights is not None:
        log.warning("--weights %s is not used: --features fpfh needs no weights", weights)
    if features == "byoc" and weights is None and default_weights_path() is None:
        raise click.UsageError(
            "--features byoc needs --weights PATH (this install ships no trained weights); "
            "or use --features fpfh"
        )
    return Registrar(device=device, recipe=recipe)


def pairwise_setup(recipe, device: str) -> tuple[Any, Any, dict | None]:
    """The extractor and the registration settings of ``recipe`` without its refinement
    (``register-scans`` and ``odometry`` refine on their own), for commands that register
    many clouds with the pipeline directly.

    Returns:
        ``(extractor, RegisterConfig, weights_info | None)``.
    """
    from byoc_cli.pipeline.register import register_config

    made = registrar(recipe, device)
    return made.extractor, register_config(recipe, refine=False), made.weights_info


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


def known_unit(result, pair: tuple[Path, Path], factors_given: bool) -> str | None:
    """``"m"`` when the points a registration measured its voxel and inlier threshold in are
    known to be metres, else None (the inputs' own units, whatever they are).

    Known: a factor to metres was given for both clouds (``factors_given``: ``--scale``, or
    ``--source-scale`` and ``--target-scale``), both inputs are depth
    images (their depth scale gives metres), the features' own voxel was asked for (``own``:
    the inputs are checked to look like metres), or the auto voxel found scans of the size
    the features were trained on and kept their own voxel (its unit check). A voxel the auto
    path scaled (millimetres, objects, LiDAR) or a number given leaves the unit unknown.
    """
    if factors_given:
        return "m"
    if all(Path(p).suffix.lower() in DEPTH_EXTENSIONS for p in pair):
        return "m"
    voxel = (result.recipe or {}).get("features", {}).get("voxel")
    choice = result.voxel_choice
    if voxel == "own":
        return "m"
    if choice is not None and choice["refine_voxel_size"] == choice["reference_voxel_size"]:
        return "m"
    return None


def depth_scale_used(path: Path, given: float | None) -> float | None:
    """The depth scale a depth-image input was read with (the option's, else its layout's,
    else 1000: :func:`byoc_cli.pipeline.inputs.depth_scale_of`); None for a point cloud."""
    if Path(path).suffix.lower() not in DEPTH_EXTENSIONS:
        return None
    from byoc_cli.pipeline.inputs import depth_scale_of

    value, source = depth_scale_of(path, given)
    log.info("%s: depth scale %g (%s)", path, value, source)
    return value


def format_length(value: float, unit: str | None) -> str:
    """A length for a message: ``5.0 cm`` or ``0.025 m`` in metres, ``51.6 input units``
    when the unit is not known (:func:`known_unit`)."""
    if unit != "m":
        return f"{value:.4g} input units"
    return f"{100 * value:.1f} cm" if value < 1 else f"{value:.4g} m"


def registration_report(result, registrar, pair: tuple[Path, Path], run: dict) -> dict:
    """The JSON report of one registration (``register --json``, a line of the batch
    summary); ``run``: ``min_confidence``, ``scale``, ``device`` and ``started`` (the
    ``perf_counter`` the command started at), ``init_file`` (the initial pose's file, or
    None), ``factors``: each cloud's factor to metres
    (:func:`cloud_factors`) and ``factors_given``: whether both were given. ``voxel_size``
    and ``inlier_threshold`` are in the units ``unit`` names: ``"m"``, or None for the
    inputs' own (:func:`known_unit`)."""
    import time

    from byoc_cli import __version__

    timings = {**result.timings, "command": time.perf_counter() - run["started"]}
    init = result.init
    if init is not None and run.get("init_file") is not None:
        init = {"file": str(run["init_file"]), **init}
    return {
        "source": str(pair[0]),
        "target": str(pair[1]),
        "T_tgt_src": result.T_tgt_src.tolist(),
        "convention": "x_tgt = R x_src + t; T is 4x4 on column vectors",
        "path": result.path,
        "init": init,
        "features": result.features,
        "estimator": result.estimator,
        "refine": result.refine,
        "num_points_src": result.num_points_src,
        "num_points_tgt": result.num_points_tgt,
        "num_correspondences": result.num_correspondences,
        "num_inliers": result.num_inliers,
        "inlier_ratio": result.inlier_ratio,
        "inlier_threshold": result.inlier_threshold,
        "overlap": result.overlap,
        "confidence": result.confidence,
        "cues": result.cues,
        "min_confidence": run["min_confidence"],
        "passed": result.passed,
        "voxel_size": result.voxel_size,
        "unit": known_unit(result, pair, run["factors_given"]),
        "voxel_choice": result.voxel_choice,
        "fallback": result.fallback,
        "features_choice": result.features_choice,
        "turns": result.turns,
        "reproduced": result.reproduced,
        "retries": result.retries,
        "check": result.check,
        "visibility": result.visibility,
        "scale": run["scale"],
        "depth_scale": [depth_scale_used(p, run.get("depth_scale")) for p in pair],
        "source_scale": run["factors"][0],
        "target_scale": run["factors"][1],
        "max_points": result.max_points,
        "seed": result.seed,
        "recipe": result.recipe,
        "device": run["device"],
        "weights": registrar.weights_info,
        "weights_sha256": result.weights_sha256,
        "byoc_cli_version": __version__,
        "timings_s": timings,
    }


class StageProgress:
    """Progress bars on stderr per stage (only on a terminal and without -q)."""

    def __init__(self, quiet: bool) -> None:
        import sys

        self.progress = progress_bar() if not is_quiet(quiet) and sys.stderr.isatty() else None
        self.tasks: dict[str, Any] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if self.progress is None:
            return
        if stage not in self.tasks:
            self.tasks[stage] = self.progress.add_task(stage, total=total)
        self.progress.update(self.tasks[stage], completed=done)

    def close(self) -> None:
        if self.progress is not None:
            self.progress.__exit__(None, None, None)


def ambiguity(turns: dict) -> str:
    """``ambiguous: ...`` of a result's ``turns`` report: the confidences of the tries that end
    apart (:mod:`byoc_cli.pipeline.turns`)."""
    tries = sorted(turns["tries"], key=lambda t: -t["confidence"])
    shown = ", ".join(f"{t['confidence']:.3f} turned {t['degrees']:g} deg" for t in tries[:3])
    return f"ambiguous: the source fits at more than one pose (confidences {shown})"


def turned_rival(cues: dict | None) -> str | None:
    """``ambiguous: ...`` of a result whose structure check
    (:mod:`byoc_cli.pipeline.structure_check`) found a turn about the up axis that fits what
    is not floor, ceiling or wall as well as the result; None otherwise."""
    from byoc_cli.pipeline.structure_check import RIVAL_MARGIN

    rival = (cues or {}).get("structure_rival")
    if not isinstance(rival, float) or not rival > -RIVAL_MARGIN:
        return None
    return (
        "ambiguous: the source turned about the up axis fits what stands in the scene as well "
        f"as under T (clutter fit {rival:+.2f} against T's; {-RIVAL_MARGIN:+.2f} at most)"
    )


def seen_through(visibility: dict) -> str:
    """``inconsistent: ...`` of a result's ``visibility`` report
    (:mod:`byoc_cli.pipeline.visibility`): how much of each cloud lies in the other's free
    space."""
    return (
        f"inconsistent: under T {visibility['source_in_target']:.0%} of the source lies in space "
        f"the target's sensor saw empty, {visibility['target_in_source']:.0%} of the target in "
        f"the source's (at most {visibility['max_free_space']:.0%}; sensors at the clouds' "
        "origins, --no-visibility if they are not)"
    )


def check_ambiguity(check: dict, unit: str | None) -> str:
    """``ambiguous: ...`` of a result's ``check`` report (:mod:`byoc_cli.pipeline.recheck`):
    where the two seeds put the source, and their confidences."""
    first, second = check["alternatives"]
    gap = check["apart"]
    return (
        f"ambiguous: seeds {first['seed']} and {second['seed']} fit the source "
        f"{gap['rotation_deg']:.1f} deg / {format_length(gap['translation'], unit)} apart "
        f"(confidences {first['confidence']:.3f} and {second['confidence']:.3f})"
    )
