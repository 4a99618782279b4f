"""``byoc make-fragments``: turn a posed RGB-D sequence into a 3DMatch-layout benchmark."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import click

from byoc_cli import limits
from byoc_cli.cli.display import is_quiet
from byoc_cli.cli.errors import CliError, handle_errors
from byoc_cli.cli.options import (
    DEPTH_SCALE,
    LENGTH,
    TSDF_VOXEL,
    finite_float,
    verbosity_options,
)

_PATH = click.Path(path_type=Path)


def _scene_name(rgbd_dir: Path, sequence) -> str:
    """The sequence's folder name, prefixed by ``--rgbd-dir``'s when it lies below it."""
    root = rgbd_dir.resolve()
    if sequence.root.resolve() == root:
        return root.name
    return f"{root.name}-{sequence.name.replace('/', '-')}"


def _load_sequence(rgbd_dir: Path, intrinsics: Path | None, depth_scale: float | None):
    from byoc_cli.io.rgbd import discover_sequences

    sequences = discover_sequences(
        rgbd_dir, intrinsics=intrinsics, depth_scale=depth_scale, require_poses=True
    )
    if len(sequences) > 1:
        names = ", ".join(s.name for s in sequences[:3])
        raise CliError(
            f"{rgbd_dir}: holds {len(sequences)} RGB-D sequences ({names}, ...); "
            "pass the folder of one"
        )
    return sequences[0]


@click.command(
    "make-fragments",
    epilog="Writes OUT/<scene>/cloud_bin_K.ply, OUT/<scene>-evaluation/{gt.log, gt.info, "
    "gt_overlap.log} and OUT/make-fragments.json; evaluate with `byoc eval-fmr OUT`. Exit "
    "codes: 0 written; 1 bad input (no poses, OUT not empty, unreadable frame); 2 usage error.",
)
@click.option(
    "--rgbd-dir",
    required=True,
    type=_PATH,
    help="One RGB-D sequence WITH poses (TUM groundtruth.txt, 3DMatch/7-Scenes pose.txt, "
    "ScanNet pose/); depth alone is enough.",
)
@click.option(
    "--out",
    required=True,
    type=_PATH,
    help="Benchmark folder to create (must not exist or be empty).",
)
@click.option("--scene", default=None, help="Scene name [default: the sequence's folder name].")
@click.option(
    "--frames-per-fragment",
    type=click.IntRange(min=1),
    default=50,
    show_default=True,
    help="Depth frames fused per fragment (3DMatch: 50 at 30 Hz).",
)
@click.option(
    "--stride",
    type=click.IntRange(min=1),
    default=None,
    help="A fragment starts every STRIDE frames [default: --frames-per-fragment, "
    "non-overlapping windows].",
)
@click.option(
    "--tsdf-voxel",
    type=TSDF_VOXEL,
    default=0.006,
    show_default=True,
    help="TSDF voxel in metres (3DMatch: 6 mm).",
)
@click.option(
    "--sdf-trunc",
    type=LENGTH,
    default=0.04,
    show_default=True,
    help="TSDF truncation distance in metres.",
)
@click.option(
    "--depth-trunc",
    type=LENGTH,
    default=3.0,
    show_default=True,
    help="Ignore depth beyond this, metres.",
)
@click.option(
    "--min-overlap",
    type=finite_float(0, 1, max_open=True),
    default=0.3,
    show_default=True,
    help="gt.log keeps the pairs whose overlap is above this (3DLoMatch: 0.1).",
)
@click.option(
    "--max-overlap",
    type=finite_float(0, 1, min_open=True),
    default=1.0,
    show_default=True,
    help="... and at most this: '--min-overlap 0.1 --max-overlap 0.3' is a 3DLoMatch-style "
    "low-overlap benchmark; 1 keeps every pair above --min-overlap.",
)
@click.option(
    "--intrinsics",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Intrinsics file for a sequence that ships none.",
)
@click.option(
    "--depth-scale",
    type=DEPTH_SCALE,
    default=None,
    help="Depth units per metre [default: the layout's convention].",
)
@verbosity_options
@handle_errors
def make_fragments(
    rgbd_dir: Path,
    out: Path,
    scene: str | None,
    intrinsics: Path | None,
    depth_scale: float | None,
    **fusion: Any,
) -> None:
    """Fuse every N frames of a posed RGB-D sequence into a fragment (TSDF, 3DMatch recipe)
    and write the 3DMatch benchmark layout with gt.log, gt.info and gt_overlap.log.

    Each fragment is in the camera frame of its first frame; gt.log lists the pairs i < j
    whose overlap exceeds --min-overlap and is at most --max-overlap, with the matrix that
    maps fragment j into i.
    Progress goes to stderr, a one-line summary to stdout.
    """
    from byoc_cli.pipeline.fragments import FragmentSettings, make_fragment_benchmark

    fusion["voxel_size"] = fusion.pop("tsdf_voxel")
    settings = FragmentSettings(**fusion)
    tsdf_voxel, sdf_trunc = settings.voxel_size, settings.sdf_trunc
    min_overlap, max_overlap = settings.min_overlap, settings.max_overlap
    if sdf_trunc <= tsdf_voxel:
        raise click.BadParameter(
            f"must exceed --tsdf-voxel ({tsdf_voxel})", param_hint="'--sdf-trunc'"
        )
    if sdf_trunc > limits.MAX_TRUNC_VOXELS * tsdf_voxel:
        raise click.BadParameter(
            f"must be at most {limits.MAX_TRUNC_VOXELS:g} times --tsdf-voxel "
            f"({limits.MAX_TRUNC_VOXELS * tsdf_voxel:g} m): the memory grows with it",
            param_hint="'--sdf-trunc'",
        )
    if max_overlap <= min_overlap:
        raise click.BadParameter(
            f"must exceed --min-overlap ({min_overlap:g})", param_hint="'--max-overlap'"
        )
    start = time.perf_counter()
    sequence = _load_sequence(rgbd_dir, intrinsics, depth_scale)
    if scene is None:
        scene = _scene_name(rgbd_dir, sequence)
    quiet = is_quiet(False)
    if sequence.num_skipped and not quiet:
        click.echo(
            f"byoc: {sequence.num_skipped} frames skipped (no depth file or no pose)", err=True
        )

    def on_fragment(info, total: int) -> None:
        if quiet:
            return
        click.echo(
            f"byoc: fragment {info.index + 1}/{total}: frames {info.frames[0]}-"
            f"{info.frames[-1]}, {info.num_points} points "
            f"({time.perf_counter() - start:.0f} s)",
            err=True,
        )

    try:
        result = make_fragment_benchmark(
            sequence, out, scene=scene, on_fragment=on_fragment, **fusion
        )
    except ValueError as exc:
        if "scene name" in str(exc):
            raise click.BadParameter(str(exc), param_hint="'--scene'") from exc
        raise CliError(str(exc)) from exc
    band = f"> {min_overlap:g}" if max_overlap >= 1 else f"in ({min_overlap:g}, {max_overlap:g}]"
    click.echo(
        f"{result.out_dir}: scene {result.scene}, {len(result.fragments)} fragments, "
        f"{len(result.pairs)} pairs with overlap {band} "
        f"(of {result.num_candidate_pairs}), {time.perf_counter() - start:.0f} s"
    )
