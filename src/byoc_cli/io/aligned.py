"""The moved source of a registration (``byoc register --aligned``), in the format its file
name asks for: binary PLY (``.ply``, any other name, or standard output), LAS/LAZ (``.las``,
``.laz``: a copy of a LAS/LAZ source's header and point records with new x, y, z) or E57
(``.e57``: one scan of x, y, z).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from byoc_cli.errors import InputError
from byoc_cli.io.cloudpath import parse_cloud_path
from byoc_cli.io.las import LAS_EXTENSIONS

__all__ = ["aligned_format", "write_aligned"]


def aligned_format(path: str | os.PathLike[str], source: str | os.PathLike[str]) -> str:
    """The format ``--aligned path`` is written in for the source ``source``: ``"las"``,
    ``"e57"`` or ``"ply"`` (any other extension); checked before the work starts.

    Raises:
        InputError: naming ``path``: a ``.las``/``.laz`` output for a source that is not
            LAS/LAZ (the header and point records to copy come from the source).
    """
    suffix = Path(path).suffix.lower()
    if suffix in LAS_EXTENSIONS:
        file = parse_cloud_path(source).file
        if file.suffix.lower() not in LAS_EXTENSIONS:
            raise InputError(
                path,
                f"a LAS/LAZ output copies the header and point records of a LAS/LAZ source, "
                f"and the source {source} is not one; write .ply or .e57 instead",
            )
        return "las"
    if suffix == ".e57":
        return "e57"
    return "ply"


def write_aligned(
    path: str | os.PathLike[str], points: np.ndarray, source: str | os.PathLike[str]
) -> None:
    """Write the moved source ``points`` to ``path`` in :func:`aligned_format`, atomically.

    Args:
        path: the output file.
        points: ``(N, 3)`` the source's points as read, moved by ``T_tgt_src``; for a LAS
            source, row k is the source's point record k.
        source: the source the points were read from (a LAS output copies its records).

    Raises:
        InputError: as :func:`aligned_format`, or the file cannot be written.
        ShapeError: ``points`` do not match the LAS source's records, or do not fit LAS's
            coordinates.
    """
    fmt = aligned_format(path, source)
    if fmt == "las":
        from byoc_cli.io.las import write_las_like

        write_las_like(path, parse_cloud_path(source).file, points)
    elif fmt == "e57":
        from byoc_cli.io.e57 import write_e57

        write_e57(path, points, name=f"{Path(source).name} aligned by byoc")
    else:
        from byoc_cli.io.ply import write_ply

        write_ply(path, points)
