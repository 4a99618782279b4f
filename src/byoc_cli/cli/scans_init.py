"""``register-scans``' initial poses and the frame its scans are registered in.

The frame: scans far from the origin are registered about the first scan's middle, and scans
of another size at the features' scale; poses come back in the input's coordinates
(:func:`about_first`, :func:`about`, :func:`unscaled`). The initial poses (``--init-poses``,
or the stored poses of an E57 file's scans) are read here, checked against the scans before
any work, and brought into that frame (:func:`in_frame`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, NamedTuple

import click

from byoc_cli.cli.display import is_quiet
from byoc_cli.cli.options import apply
from byoc_cli.cli.pairwise import MAX_CORRECTION_DEG, MaxCorrection

log = logging.getLogger("byoc")

#: the options of ``register-scans`` that give and bound initial poses
init_poses_options = apply(
    click.option(
        "--init-poses",
        metavar="TRAJ|none",
        default=None,
        help="Initial poses: a TUM trajectory (timestamp tx ty tz qx qy qz qw, sorted by "
        "timestamp) or a .log (3DMatch/Open3D), one T_world_scan per scan in the order given "
        "(the scan as register-scans reads it). Each overlapping pair is refined from its "
        "relative pose, without features (docs/poses.md). The scans of one E57 file start "
        "from their stored poses without it; 'none' registers them without.",
    ),
    click.option(
        "--max-correction",
        type=MaxCorrection(),
        default=None,
        help="With initial poses: how far a pair may move from its relative pose, degrees and "
        "the distance its source's centroid moves (input units); beyond it the pair is no "
        f"edge [default: {MAX_CORRECTION_DEG:g} deg and 20 refinement voxels, 50 ICP voxels: "
        "1 m at --icp-voxel 0.02].",
    ),
)


class ScansInit(NamedTuple):
    """Initial poses of the scans.

    Attributes:
        poses: ``(N, 4, 4)`` float64 ``T_world_scan`` per scan, input units.
        source: ``"file"`` (``--init-poses``) or ``"e57"`` (the scans' stored poses).
        path: the trajectory or the E57 file.
        format: ``"tum"``, ``"log"`` or ``"e57"``.
        max_correction: ``(degrees, distance in input units or None)``, or None.
    """

    poses: Any
    source: str
    path: Path
    format: str
    max_correction: tuple | None


def resolve_init(scans: list[Path], init_poses: str | None, max_correction) -> ScansInit | None:
    """The initial poses of ``scans`` (None: none), read and checked before any work.

    Raises:
        InputError: a trajectory that cannot be read, is malformed, or holds another number
            of poses than there are scans.
        click.UsageError: ``--max-correction`` without initial poses.
    """
    import numpy as np

    from byoc_cli.errors import InputError

    init = None
    if init_poses is not None and init_poses.strip().lower() != "none":
        from byoc_cli.io.trajectory import read_trajectory

        path = Path(init_poses)
        given = read_trajectory(path)
        if len(given.poses) != len(scans):
            raise InputError(
                path, f"holds {len(given.poses)} poses for {len(scans)} scans (one "
                "T_world_scan per scan, in the order given)",
            )  # fmt: skip
        init = ScansInit(given.poses, "file", path, given.format, max_correction)
    elif init_poses is None and (e57 := _posed_e57(scans)) is not None:
        identity = np.tile(np.eye(4), (len(scans), 1, 1))  # the poses are applied on reading
        init = ScansInit(identity, "e57", e57, "e57", max_correction)
    if init is None and max_correction is not None:
        raise click.UsageError("--max-correction goes with initial poses (--init-poses)")
    return init


def _posed_e57(scans: list[Path]) -> Path | None:
    """The E57 file whose scans ``scans`` all are, when each of them stores a pose; else None."""
    from byoc_cli.io.cloudpath import parse_cloud_path
    from byoc_cli.io.e57 import read_e57_poses

    parsed = [parse_cloud_path(path) for path in scans]
    files = {p.file for p in parsed}
    if len(files) != 1 or any(p.scan is None for p in parsed):
        return None
    (file,) = files
    stored = read_e57_poses(file, stored_only=True)
    return file if all(stored[p.scan] is not None for p in parsed) else None


def announce(init: ScansInit | None, quiet: bool) -> None:
    """Say on stderr that an E57 file's stored poses are the initial poses."""
    if init is not None and init.source == "e57" and not is_quiet(quiet):
        click.echo(
            f"byoc: {init.path}: starting from the scans' stored poses (--init-poses none: "
            "without them)",
            err=True,
        )


def register(points, labels, setup: tuple, init: ScansInit | None, scale: float, report):
    """Register ``points`` (the scans in the frame of :func:`about_first`, times ``scale``)
    with ``setup`` ``(extractor, register_config, ScansConfig, progress)``: without
    ``init``, :func:`~byoc_cli.pipeline.scans.register_scans`; with it,
    :func:`~byoc_cli.pipeline.scans_init.register_scans_from_poses` from its poses (in that
    frame, :func:`in_frame`). When an E57 file's stored poses leave scans unplaced, the scans
    are registered again without them. ``report`` takes ``(key, value)`` of the report.

    Returns:
        the :class:`~byoc_cli.pipeline.scans.ScansResult`.
    """
    import torch

    from byoc_cli.pipeline.local import TrustRegion
    from byoc_cli.pipeline.scans import register_scans
    from byoc_cli.pipeline.scans_init import register_scans_from_poses

    extractor, register_config, config, progress, origin = setup
    workers = torch.get_num_threads()  # byoc --threads: pairs side by side
    if init is None:
        report("init_poses", None)
        return register_scans(
            points, extractor, register_config, config, labels, progress, workers=workers
        )
    trust = TrustRegion()
    if init.max_correction is not None:
        degrees, distance = init.max_correction
        trust = TrustRegion(degrees, None if distance is None else distance * scale)
    poses = in_frame(init.poses, origin, scale)
    result = register_scans_from_poses(points, poses, config, trust, labels, progress, workers)
    region = trust.resolved(refine_voxel(config), 1.0)
    entry = {
        "source": init.source,
        "path": str(init.path),
        "format": init.format,
        "trust_region": {
            "rotation_deg": region.rotation_deg,
            "translation": region.translation / scale,
        },
        "used": True,
    }
    if init.source == "e57" and result.unplaced:
        entry["used"] = False
        log.warning(
            "%s: the stored poses left %d of %d scans unplaced: registering without them",
            init.path, len(result.unplaced), len(points),
        )  # fmt: skip
        result = register_scans(
            points, extractor, register_config, config, labels, progress, workers=workers
        )
    report("init_poses", entry)
    return result


def refine_voxel(config) -> float:
    """The refinement voxel of ``register-scans``' pairs (the trust region's unit)."""
    from byoc_cli.pipeline.refine_pairs import FINE_VOXEL

    return config.icp_voxel / FINE_VOXEL


def pair_init_json(init: dict | None, unit: float) -> dict | None:
    """A pair's ``init`` as the report writes it: the correction (its translation in input
    units: times ``unit``) and whether it lies inside the trust region."""
    if init is None:
        return None
    moved = init["correction"]
    return {
        "correction": {
            "rotation_deg": moved["rotation_deg"],
            "translation": moved["translation"] * unit,
        },
        "inside_trust_region": init["inside_trust_region"],
    }


def in_frame(poses, origin, scale: float):
    """``T_world_scan`` per scan (input units) as poses of the scans moved by ``-origin`` after
    scaling by ``scale`` (``x' = s x - o``): ``[R | R o + s t - o]``, about a world moved the
    same way; relative poses are those of the moved scans."""
    import numpy as np

    out = np.array(poses, dtype=np.float64)
    for T in out:
        T[:3, 3] = T[:3, :3] @ origin + scale * T[:3, 3] - origin
    return out


def about_first(points: list):
    """``(origin (3,), points)``: scans far from the origin (georeferenced: the first scan's
    median point more than 100 of its radii out, :func:`~byoc_cli.geometry.sampling.local_frame`)
    moved by the first scan's median point, subtracted in float64; else zeros and the scans."""
    import numpy as np

    from byoc_cli.geometry.sampling import local_frame

    origin = local_frame(points[0]).origin
    if not np.any(origin):
        return np.zeros(3), points
    return origin, [p - origin for p in points]


def about(T, origin):
    """``T (4, 4)`` between clouds moved by ``-origin``, as a transform of the clouds where they
    were: ``x' = R (x - o) + t + o``."""
    T = T.copy()
    T[:3, 3] += origin - T[:3, :3] @ origin
    return T


def unscaled(T, unit: float):
    """``T (4, 4)`` with its translation times ``unit``."""
    T = T.copy()
    T[:3, 3] *= unit
    return T
