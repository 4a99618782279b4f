"""The 3DMatch geometric registration benchmark: ground-truth files, scenes, prepared pairs.

Files (official layout, also 3DLoMatch):

``gt.log``
    Records of five lines: ``i j n`` (fragment ``i``, fragment ``j``, number of fragments of
    the scene), then a 4x4 matrix. **Direction:** the matrix maps the points of fragment
    ``j`` into the frame of fragment ``i``, so in this project's convention it is
    ``T_tgt_src`` with source ``j`` and target ``i``: ``x_i = R x_j + t``. (The 3DMatch
    toolbox and FCGF read it the same way: FCGF moves fragment ``i`` with ``inv(T)``.)
``gt.info``
    Records of seven lines: ``i j n``, then the 6x6 information matrix of the pair, used by the
    official registration recall (:func:`byoc_cli.evaluation.metrics.registration_rmse`).
``gt_overlap.log``
    Lines ``i,j,overlap`` (3DLoMatch / Predator).

Layouts of a benchmark root (:func:`discover_benchmark`): fragments in
``ROOT/<scene>/cloud_bin_K.ply`` and ground truth in ``ROOT/<scene>-evaluation/`` (the official
download), or ground truth directly in ``ROOT/<scene>/`` (``benchmarks/3DMatch/<scene>/`` of the
Predator-style ground-truth folders). A separate ground-truth folder (``gt_dir``) with either
sub-layout supplies what the root lacks (typically ``gt.info``).

Prepared pairs (:func:`discover_prepared_pairs`): ``ROOT/NNNN/{source.ply, target.ply,
T_gt.txt}``, ``T_gt`` mapping source into target; ``ROOT`` itself may be one such folder.

Depends on numpy and :mod:`byoc_cli.errors` only.
"""

from __future__ import annotations

import io
import itertools
import math
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from byoc_cli.errors import DatasetError, InputError
from byoc_cli.io.inputs import read_input

__all__ = [
    "EVALUATION_SUFFIX",
    "BenchmarkScene",
    "GtInfoRecord",
    "GtRecord",
    "PreparedPair",
    "discover_benchmark",
    "discover_prepared_pairs",
    "fragment_path",
    "read_gt_info",
    "read_gt_log",
    "read_gt_overlap",
]

#: Suffix of the official ground-truth folder of a scene.
EVALUATION_SUFFIX = "-evaluation"
#: Largest accepted ``max |R^T R - I|`` in gt.log (its 9 significant digits reach 5.1e-4).
ORTHONORMAL_TOL = 1e-3
#: Tolerance on the last row ``0 0 0 1`` of a gt.log matrix.
LAST_ROW_TOL = 1e-6

_FRAGMENT = re.compile(r"^cloud_bin_(\d+)\.ply$")


class GtRecord(NamedTuple):
    """One ``gt.log`` record.

    Attributes:
        i: target fragment (the frame the matrix maps into).
        j: source fragment (the points the matrix moves).
        num_fragments: the third header number ``n`` (fragments of the scene).
        T_tgt_src: ``(4, 4)`` float64, maps fragment ``j`` into fragment ``i``'s frame.
        line: 1-based line number of the record's header in the file.
    """

    i: int
    j: int
    num_fragments: int
    T_tgt_src: np.ndarray
    line: int


class GtInfoRecord(NamedTuple):
    """One ``gt.info`` record.

    Attributes:
        i, j: fragments, as in :class:`GtRecord`.
        num_fragments: the third header number.
        info: ``(6, 6)`` float64 information matrix.
        line: 1-based line number of the record's header.
    """

    i: int
    j: int
    num_fragments: int
    info: np.ndarray
    line: int


class BenchmarkScene(NamedTuple):
    """One scene of a 3DMatch-layout benchmark.

    Attributes:
        name: scene name (``7-scenes-redkitchen``).
        fragment_dir: where ``cloud_bin_K.ply`` are (may not exist: ground truth only).
        gt_log: the ``gt.log`` used.
        gt_info: the ``gt.info`` used, or None when none was found.
        gt_overlap: the ``gt_overlap.log``, or None.
    """

    name: str
    fragment_dir: Path
    gt_log: Path
    gt_info: Path | None
    gt_overlap: Path | None


class PreparedPair(NamedTuple):
    """A prepared pair folder.

    Attributes:
        name: folder name (``0000``).
        source, target: the two PLY files.
        T_gt: ``(4, 4)`` float64 ``T_tgt_src`` read from ``T_gt.txt``.
    """

    name: str
    source: Path
    target: Path
    T_gt: np.ndarray


# ================================================================== parsing


def _read_lines(path: Path) -> Iterator[str]:
    """The lines of ``path``, one at a time (millions of short lines never exist at once)."""
    raw = read_input(path, "benchmark")
    try:
        return iter(io.StringIO(raw.decode("utf-8-sig"), newline=None))
    except UnicodeDecodeError as exc:
        raise InputError(path, "not a text file") from exc


def _numbers(path: Path, number: int, line: str, count: int, what: str) -> list[float]:
    parts = line.replace(",", " ").split()
    if len(parts) != count:
        raise InputError(
            path, f"line {number}: expected {count} numbers ({what}), found {len(parts)}"
        )
    try:
        values = [float(v) for v in parts]
    except ValueError as exc:
        raise InputError(path, f"line {number}: not a number in {line.strip()[:40]!r}") from exc
    if not all(math.isfinite(v) for v in values):
        raise InputError(path, f"line {number}: NaN or Inf")
    return values


def _header(path: Path, number: int, line: str) -> tuple[int, int, int]:
    values = _numbers(path, number, line, 3, "record header 'i j n'")
    if any(v != int(v) or v < 0 for v in values):
        raise InputError(path, f"line {number}: header 'i j n' must be non-negative integers")
    i, j, n = (int(v) for v in values)
    if i == j:
        raise InputError(path, f"line {number}: pair of a fragment with itself ({i} {j})")
    if max(i, j) >= n:
        raise InputError(
            path, f"line {number}: fragment {max(i, j)} out of range for n = {n} fragments"
        )
    return i, j, n


def _records(path: Path, rows: int) -> Iterator[tuple[int, tuple[int, int, int], np.ndarray]]:
    """``(header line, (i, j, n), (rows, rows) matrix)`` one record at a time, in file order;
    blank lines are skipped."""
    numbered = ((k, line) for k, line in enumerate(_read_lines(path), start=1) if line.strip())
    while chunk := list(itertools.islice(numbered, rows + 1)):
        number, line = chunk[0]
        header = _header(path, number, line)
        if len(chunk) < rows + 1:
            raise InputError(
                path,
                f"line {number}: record truncated ({len(chunk) - 1} of {rows} matrix rows "
                "before the end of the file)",
            )
        matrix = np.array(
            [_numbers(path, k, text, rows, "matrix row") for k, text in chunk[1:]],
            dtype=np.float64,
        )
        yield number, header, matrix


def read_gt_log(path: str | os.PathLike[str]) -> list[GtRecord]:
    """Parse a 3DMatch ``gt.log``.

    Args:
        path: the file.

    Returns:
        The records in file order; ``T_tgt_src`` maps fragment ``j`` into fragment ``i``.

    Raises:
        InputError: missing or unreadable file, or a malformed record; the problem names the
            line (wrong count of numbers, non-numeric, NaN/Inf, header not integers, a pair
            of a fragment with itself, ``i`` or ``j`` not below ``n``, a last row other than
            ``0 0 0 1``, a rotation block that is not a rotation, a duplicate pair, a
            truncated record).
    """
    path = Path(path)
    out: list[GtRecord] = []
    seen: dict[tuple[int, int], int] = {}
    for number, (i, j, n), T in _records(path, 4):
        if np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0])) > LAST_ROW_TOL:
            raise InputError(path, f"line {number + 4}: last matrix row is not '0 0 0 1'")
        R = T[:3, :3]
        error = float(np.max(np.abs(R.T @ R - np.eye(3))))
        if error > ORTHONORMAL_TOL or np.linalg.det(R) < 0:
            raise InputError(
                path, f"line {number + 1}: the matrix of pair {i} {j} is not a rigid transform"
            )
        if (i, j) in seen:
            raise InputError(
                path, f"line {number}: pair {i} {j} repeats the record of line {seen[(i, j)]}"
            )
        seen[(i, j)] = number
        out.append(GtRecord(i, j, n, T, number))
    return out


def read_gt_info(path: str | os.PathLike[str]) -> list[GtInfoRecord]:
    """Parse a 3DMatch ``gt.info`` (6x6 information matrix per pair).

    Raises:
        InputError: missing or unreadable file, or a malformed record (the line is named).
    """
    path = Path(path)
    out = []
    for number, (i, j, n), info in _records(path, 6):
        out.append(GtInfoRecord(i, j, n, info, number))
    return out


def read_gt_overlap(path: str | os.PathLike[str]) -> dict[tuple[int, int], float]:
    """Parse a ``gt_overlap.log`` (lines ``i,j,overlap``).

    Returns:
        ``{(i, j): overlap}``.

    Raises:
        InputError: missing or unreadable file, or a malformed line.
    """
    path = Path(path)
    out = {}
    for number, line in enumerate(_read_lines(path), start=1):
        if not line.strip():
            continue
        i, j, overlap = _numbers(path, number, line, 3, "'i,j,overlap'")
        if i != int(i) or j != int(j):
            raise InputError(path, f"line {number}: fragment numbers must be integers")
        out[(int(i), int(j))] = overlap
    return out


# ================================================================== discovery


def fragment_path(scene: BenchmarkScene, k: int) -> Path:
    """``<fragment_dir>/cloud_bin_<k>.ply``."""
    return scene.fragment_dir / f"cloud_bin_{k}.ply"


def _first_file(candidates: list[Path]) -> Path | None:
    return next((c for c in candidates if c.is_file()), None)


def _has_fragments(folder: Path) -> bool:
    try:
        return any(_FRAGMENT.match(entry.name) for entry in os.scandir(folder))
    except OSError:
        return False


def _gt_folders(name: str, root: Path, gt_dir: Path | None) -> list[Path]:
    folders = [root / f"{name}{EVALUATION_SUFFIX}", root / name]
    if gt_dir is not None:
        folders += [gt_dir / f"{name}{EVALUATION_SUFFIX}", gt_dir / name]
    return folders


def discover_benchmark(
    root: str | os.PathLike[str], gt_dir: str | os.PathLike[str] | None = None
) -> list[BenchmarkScene]:
    """Find the scenes of a 3DMatch-layout benchmark.

    A scene is a folder ``ROOT/<scene>-evaluation/`` or a folder ``ROOT/<scene>/`` holding a
    ``gt.log`` or ``cloud_bin_K.ply`` fragments. Each ground-truth file is taken from the
    first of ``ROOT/<scene>-evaluation/``, ``ROOT/<scene>/``, ``GT/<scene>-evaluation/``,
    ``GT/<scene>/`` that has it (``GT`` = ``gt_dir``).

    Args:
        root: the benchmark folder (``.../3DMatch``).
        gt_dir: optional ground-truth folder (``benchmarks/3DMatch``) for what ``root`` lacks.

    Returns:
        Scenes sorted by name (never empty).

    Raises:
        DatasetError: ``root`` (or ``gt_dir``) is missing or not a folder; no scene is found;
            a scene has fragments but no ``gt.log``.
    """
    root = Path(root)
    for folder, label in ((root, "benchmark folder"), (gt_dir, "ground-truth folder")):
        if folder is None:
            continue
        folder = Path(folder)
        if not folder.exists():
            raise DatasetError(folder, f"{label} does not exist")
        if not folder.is_dir():
            raise DatasetError(folder, f"{label} is not a folder")
    gt_dir = Path(gt_dir) if gt_dir is not None else None
    names: set[str] = set()
    for entry in sorted(os.scandir(root), key=lambda e: e.name):
        if not entry.is_dir() or entry.name.startswith("."):
            continue
        path = Path(entry.path)
        if entry.name.endswith(EVALUATION_SUFFIX) and (path / "gt.log").is_file():
            names.add(entry.name[: -len(EVALUATION_SUFFIX)])
        elif (path / "gt.log").is_file() or _has_fragments(path):
            names.add(entry.name)
    scenes = []
    for name in sorted(names):
        folders = _gt_folders(name, root, gt_dir)
        gt_log = _first_file([f / "gt.log" for f in folders])
        if gt_log is None:
            raise DatasetError(
                root / name,
                "scene has fragments but no gt.log (looked in "
                + ", ".join(str(f) for f in folders)
                + ")",
            )
        scenes.append(
            BenchmarkScene(
                name=name,
                fragment_dir=root / name,
                gt_log=gt_log,
                gt_info=_first_file([f / "gt.info" for f in folders]),
                gt_overlap=_first_file([f / "gt_overlap.log" for f in folders]),
            )
        )
    if not scenes:
        raise DatasetError(
            root,
            "no 3DMatch scene found (looked for <scene>-evaluation/gt.log and "
            "<scene>/cloud_bin_K.ply)",
        )
    return scenes


def _is_pair_folder(folder: Path) -> bool:
    return all((folder / name).is_file() for name in ("source.ply", "target.ply", "T_gt.txt"))


def discover_prepared_pairs(root: str | os.PathLike[str]) -> list[PreparedPair]:
    """Find prepared pairs ``ROOT/NNNN/{source.ply, target.ply, T_gt.txt}``.

    ``ROOT`` may itself be one pair folder. Sub-folders lacking one of the three files are
    ignored. ``T_gt.txt`` is read and validated now; the clouds are read by the caller.

    Args:
        root: a folder of pair folders, or one pair folder.

    Returns:
        Pairs sorted by folder name (never empty).

    Raises:
        DatasetError: ``root`` is missing, not a folder, or holds no pair folder.
        InputError: a ``T_gt.txt`` is not a rigid 4x4 transform.
    """
    from byoc_cli.io.matrix import read_transform

    root = Path(root)
    if not root.exists():
        raise DatasetError(root, "folder does not exist")
    if not root.is_dir():
        raise DatasetError(root, "not a folder")
    if _is_pair_folder(root):
        folders = [root]
    else:
        folders = sorted(
            (Path(e.path) for e in os.scandir(root) if e.is_dir() and not e.name.startswith(".")),
            key=lambda p: p.name,
        )
        folders = [f for f in folders if _is_pair_folder(f)]
    if not folders:
        raise DatasetError(
            root, "no prepared pair found (looked for NNNN/source.ply, target.ply, T_gt.txt)"
        )
    return [
        PreparedPair(f.name, f / "source.ply", f / "target.ply", read_transform(f / "T_gt.txt"))
        for f in folders
    ]
