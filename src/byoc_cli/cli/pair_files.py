"""The files a registered pair may write besides its T, shared by ``register`` and
``register-batch``: the moved source in the format its name asks for (``--aligned``) and the
quality files (``--qc DIR``: a PNG of the clouds overlaid after registration and a PLY of the
moved source coloured by residual, :mod:`byoc_cli.evaluation.qc`).

Imports numpy, matplotlib and the readers only inside its functions (``--help`` stays light).
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import Any

from byoc_cli.cli.options import path_option

log = logging.getLogger("byoc")

#: ``byoc register --qc DIR``
qc_option = path_option(
    "--qc",
    "qc_dir",
    file=False,
    default=None,
    help="Write quality files of the pair into this folder (created if missing): "
    "<source-stem>__<target-stem>_qc.png (the two clouds overlaid after registration in "
    "three views, and the moved source coloured by its distance to the target) and "
    "..._residual.ply (the moved source coloured by that distance).",
)

#: ``byoc register-batch --qc DIR``
batch_qc_option = path_option(
    "--qc",
    "qc_dir",
    file=False,
    default=None,
    help="Write the quality files of `byoc register --qc` for each pair registered below "
    "the gate (`--min-confidence`; not for pairs that passed, failed or were skipped) into "
    "this folder (created if missing), named after the pair's T file: <T-stem>_qc.png and "
    "<T-stem>_residual.ply.",
)


def check_pair_files(aligned: Path | None, source: Path, qc_dir: Path | None) -> None:
    """Before the work: ``--aligned`` names a format the source can be written in, and
    ``--qc`` names a folder (or a place where one can be made).

    Raises:
        InputError: naming the path: a LAS/LAZ ``--aligned`` for a source that is not
            LAS/LAZ, or a ``--qc`` that is a file.
    """
    from byoc_cli.io.aligned import aligned_format
    from byoc_cli.io.outputs import is_stdout

    if aligned is not None and not is_stdout(aligned):
        aligned_format(aligned, source)
    check_qc_dir(qc_dir)


def check_qc_dir(qc_dir: Path | None) -> None:
    """``--qc`` (None: not given) is a folder, or a folder can be made there.

    Raises:
        InputError: naming it, when it or a parent is a file.
    """
    from byoc_cli.errors import InputError

    if qc_dir is None:
        return
    folder = qc_dir
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(qc_dir, f"is not a folder (--qc): {folder} is a file")


def pair_points(path: Path, role: str, factors: tuple, load: dict):
    """One cloud of a registered pair as ``T`` applies to it: in its own units as read
    (both clouds at one factor), or (two factors) the source brought into the target's units
    and the target as read. ``role``: ``"source"`` or ``"target"``; ``load``: ``intrinsics``
    and ``depth_scale``. Warnings are not shown again (the registration showed them)."""
    from byoc_cli.pipeline.inputs import load_cloud

    src, tgt = factors
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if src == tgt:  # the cloud in its own units, as read
            return load_cloud(path, scale=src, **load) / (src or 1.0)
        if role == "source":  # brought into the target's units
            return load_cloud(path, scale=src / tgt, **load)
        return load_cloud(path, scale=1.0, **load)


def write_aligned_source(aligned: Path, source: Path, T: Any, factors: tuple, load: dict) -> None:
    """``--aligned``: the source moved by ``T`` into ``aligned`` (its extension's format,
    ``-``: PLY on stdout)."""
    from byoc_cli.cli.output import write_stdout_bytes
    from byoc_cli.io.aligned import write_aligned
    from byoc_cli.io.outputs import is_stdout
    from byoc_cli.io.ply import write_ply

    moved = pair_points(source, "source", factors, load) @ T[:3, :3].T + T[:3, 3]
    if is_stdout(aligned):
        write_stdout_bytes(write_ply(None, moved))
    else:
        write_aligned(aligned, moved, source)


def qc_name(source: Path, target: Path) -> str:
    """``<source-stem>__<target-stem>``: the quality files' prefix of ``byoc register``."""
    from byoc_cli.io.cloudpath import cloud_stem

    return f"{cloud_stem(source)}__{cloud_stem(target)}"


def write_pair_qc(policy: Any, qc_dir: Path, name: str, report: dict, load: dict) -> dict:
    """Write ``qc_dir/<name>_qc.png`` and ``qc_dir/<name>_residual.ply`` of one registered
    pair, through the output policy ``policy`` (an :class:`~byoc_cli.io.outputs.OutputSet`
    whose ``with`` block is active: the files are claimed here and committed with the run's).

    Args:
        policy: the run's output set.
        qc_dir: the folder (created when missing).
        name: the files' prefix.
        report: the pair's registration report (:func:`byoc_cli.cli.pairwise.registration_report`:
            source, target, T_tgt_src, confidence, voxel_size, unit, the scales).
        load: ``intrinsics`` and ``depth_scale`` of depth-image inputs.

    Returns:
        The ``qc`` entry of the report: the two files, the residual clip and figures.
    """
    import numpy as np

    from byoc_cli.evaluation.qc import RESIDUAL_CLIP_VOXELS, QcSettings, qc_paths, write_qc
    from byoc_cli.io.folders import new_folders

    factors = (report["source_scale"], report["target_scale"])
    source, target = Path(report["source"]), Path(report["target"])
    with new_folders(qc_dir):
        for path in qc_paths(qc_dir, name):
            policy.claim(path)
    units = factors[1] or 1.0  # the report's voxel is in metres when a factor was given
    metres = report["unit"] == "m" and units == 1.0
    gate = report["min_confidence"]
    passed = "passed" if report["passed"] else f"below --min-confidence {gate:g}"
    settings = QcSettings(
        clip=RESIDUAL_CLIP_VOXELS * report["voxel_size"] / units,
        unit="m" if metres else "input units",
        title=f"{source} -> {target}: confidence {report['confidence']:.3f} ({passed})",
    )
    done = write_qc(
        qc_dir,
        name,
        pair_points(source, "source", factors, load),
        pair_points(target, "target", factors, load),
        np.asarray(report["T_tgt_src"], dtype=np.float64),
        settings,
    )
    return {
        "png": str(done.png),
        "ply": str(done.ply),
        "residual_clip": done.clip,
        "median_residual": done.median_residual,
        "within_clip": done.within_clip,
        "unit": settings.unit,
    }


class BatchQc:
    """``register-batch --qc DIR``: the quality files of the pairs below the gate, each
    committed on its own; a pair whose files cannot be made is logged and recorded, and the
    run goes on.

    Args:
        qc_dir: the folder.
        inputs: the run's inputs (never overwritten).
        load: ``intrinsics`` and ``depth_scale`` of depth-image inputs.
    """

    def __init__(self, qc_dir: Path, inputs: list, load: dict) -> None:
        self.qc_dir, self.inputs, self.load = qc_dir, inputs, load
        self.names: set[str] = set()

    def write(self, line: int, output: Path, record: dict) -> dict:
        """The files of the pair on list line ``line`` whose T file is ``output`` and summary
        record ``record``; returns the record's ``qc`` entry (``{"error": ...}`` on failure)."""
        from byoc_cli.io.outputs import OutputSet

        name = output.stem
        if name in self.names:  # two T files of one stem in different folders
            name = f"{name}_line{line}"
        self.names.add(name)
        try:
            policy = OutputSet(self.inputs)
            with policy:
                return write_pair_qc(policy, self.qc_dir, name, record, self.load)
        except Exception as exc:  # one pair's quality files must not stop the others
            message = " ".join(str(exc).split()) or type(exc).__name__
            log.warning("line %d: no quality files: %s", line, message)
            return {"error": message}
