"""4x4 rigid transforms as text: 4 lines of 4 numbers, exact float64 round trip.

The convention is the project's one: ``T_tgt_src`` on column vectors, ``x_tgt = R x_src + t``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from byoc_cli.errors import InputError, ShapeError
from byoc_cli.io.atomic import atomic_write_text
from byoc_cli.io.pointcloud import _open_input

__all__ = ["format_transform", "read_transform", "write_transform"]

#: Tolerance on the last row ``[0, 0, 0, 1]``.
LAST_ROW_TOL = 1e-6
#: Default tolerance on ``max |R^T R - I|``. Not tighter: the official 3DMatch ground truth
#: (gt.log, 9 significant digits) has 595 of 3404 rotations beyond 1e-4, up to 5.1e-4.
ORTHONORMAL_TOL = 1e-3


def _read_text(path: Path, kind: str = "matrix") -> str:
    with _open_input(path, kind) as f:
        raw = f.read()
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(path, "not a text file") from exc


def _parse_rows(text: str, path: Path) -> list[list[float]]:
    """Rows of numbers separated by whitespace or commas; blank lines and ``#`` comments skipped."""
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        try:
            rows.append([float(v) for v in line.split()])
        except ValueError as exc:
            raise InputError(path, f"not a numeric matrix (line {number}: {line[:40]!r})") from exc
    return rows


def _shape_phrase(rows: list[list[float]]) -> str:
    if not rows:
        return "no numbers"
    widths = sorted({len(r) for r in rows})
    return f"{len(rows)} rows of {'/'.join(map(str, widths))} numbers"


def format_transform(T: np.ndarray) -> str:
    """The text :func:`write_transform` writes: 4 lines of 4 shortest-exact float64 reprs.

    Raises:
        ShapeError: ``T`` is not ``(4, 4)``.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ShapeError(f"T must be (4, 4), got {T.shape}")
    # repr(float) is the shortest string that parses back to the same float64.
    return "".join(" ".join(repr(float(x)) for x in row) + "\n" for row in T)


def write_transform(path: str | os.PathLike[str], T: np.ndarray) -> None:
    """Write a 4x4 transform as text, atomically; ``"-"`` writes to stdout.

    Each number is written as the shortest decimal that reads back to the same float64, so
    ``read_transform(write_transform(T))`` returns ``T`` bit for bit.

    Args:
        path: output file, or ``"-"`` for standard output.
        T: ``(4, 4)`` transform (converted to float64).

    Raises:
        ShapeError: ``T`` is not ``(4, 4)``.
        InputError: the file cannot be written.
    """
    text = format_transform(T)
    if str(path) == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    atomic_write_text(path, text)


def read_transform(
    path: str | os.PathLike[str], *, orthonormal_tol: float = ORTHONORMAL_TOL
) -> np.ndarray:
    """Read and validate a 4x4 rigid transform from text.

    Numbers are separated by whitespace (or commas); blank lines and ``#`` comments are
    skipped.

    Args:
        path: the file; ``-`` reads stdin (named ``stdin`` in messages).
        orthonormal_tol: largest accepted ``max |R^T R - I|`` of the rotation block.

    Returns:
        ``(4, 4)`` float64, as written (the rotation is not re-orthonormalised).

    Raises:
        InputError: missing/unreadable file, non-numeric text, not 4x4, NaN/Inf, a last row
            other than ``0 0 0 1`` (within 1e-6), a rotation block that is not orthonormal
            (``max |R^T R - I|`` above ``orthonormal_tol``) or is a reflection; the message
            names the file.
    """
    if str(path) == "-":
        path = Path("stdin")
        rows = _parse_rows(sys.stdin.read(), path)
    else:
        path = Path(path)
        rows = _parse_rows(_read_text(path), path)
    if len(rows) != 4 or any(len(r) != 4 for r in rows):
        raise InputError(path, f"expected a 4x4 matrix, found {_shape_phrase(rows)}")
    T = np.array(rows, dtype=np.float64)
    if not np.all(np.isfinite(T)):
        raise InputError(path, "transform has NaN or Inf entries")
    if np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0])) > LAST_ROW_TOL:
        last = " ".join(f"{v:g}" for v in T[3])
        raise InputError(path, f"last row is '{last}', expected '0 0 0 1'")
    R = T[:3, :3]
    error = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if error > orthonormal_tol:
        raise InputError(path, f"rotation block is not orthonormal (max |R^T R - I| = {error:.2g})")
    if np.linalg.det(R) < 0:
        raise InputError(path, "rotation block is a reflection (determinant -1)")
    return T
