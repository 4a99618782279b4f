"""Pair-list files of ``byoc register-batch``: ``source target [output [init]]`` a line.

Blank lines and ``#`` comments (whole lines, or the rest of a line) are ignored; columns are
separated by whitespace; relative paths are relative to the list file's folder. The fourth
column names a file holding an initial pose of the pair (a 4x4 ``T_tgt_src``, as the T files);
a line with one has its output column too (the third column is always the output).
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import NamedTuple

from byoc_cli.errors import InputError
from byoc_cli.io.cloudpath import cloud_stem
from byoc_cli.io.inputs import read_input

__all__ = ["MAX_PAIRS", "PairEntry", "default_output_name", "read_pair_list", "shard"]

#: Most pairs in one list: each costs a few hundred bytes of paths before the first runs.
MAX_PAIRS = 1_000_000


class PairEntry(NamedTuple):
    """One pair of a list.

    Attributes:
        index: position among the list's pairs (0-based; comments and blank lines not counted).
        line: line number in the file (1-based), for messages.
        source, target: the clouds, resolved against the list's folder.
        output: the T file of the third column (resolved the same way), or None.
        init: the initial pose's file of the fourth column (resolved the same way), or None.
    """

    index: int
    line: int
    source: Path
    target: Path
    output: Path | None
    init: Path | None = None


def _resolve(folder: Path, text: str) -> Path:
    path = Path(os.path.expanduser(text))
    return path if path.is_absolute() else folder / path


def read_pair_list(path: str | os.PathLike[str]) -> list[PairEntry]:
    """Read a pair list.

    Raises:
        InputError: naming the file (and the line): unreadable, not a regular file, larger
            than a pair list may be, not UTF-8 text, a line with fewer than 2 or more than 4
            columns, a line whose init column names its output, more than :data:`MAX_PAIRS`
            pairs, or no pair at all.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(path, "is a folder, not a pair list")
    try:
        text = read_input(path, "pair list").decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(
            path, "is not a UTF-8 text file of 'source target [output [init]]' lines"
        ) from exc
    folder = path.parent
    pairs: list[PairEntry] = []
    # one line at a time: a list of millions of short lines never exists as a list of strings
    for number, raw in enumerate(io.StringIO(text, newline=None), start=1):
        columns = raw.split("#", 1)[0].split()
        if not columns:
            continue
        if len(columns) not in (2, 3, 4):
            raise InputError(
                path,
                f"line {number}: expected 'source target [output [init]]' (an init column "
                f"comes after the output column), got {len(columns)} column(s)",
            )
        if len(pairs) == MAX_PAIRS:
            raise InputError(path, f"holds more than {MAX_PAIRS:,} pairs; split the list")
        output = _resolve(folder, columns[2]) if len(columns) >= 3 else None
        init = _resolve(folder, columns[3]) if len(columns) == 4 else None
        if init is not None and init == output:
            raise InputError(
                path, f"line {number}: the init column names the output column's file {output}"
            )
        pairs.append(
            PairEntry(
                len(pairs),
                number,
                _resolve(folder, columns[0]),
                _resolve(folder, columns[1]),
                output,
                init,
            )
        )
    if not pairs:
        raise InputError(path, "holds no pair (lines of 'source target [output [init]]')")
    return pairs


def default_output_name(source: Path, target: Path) -> str:
    """``<source-stem>__<target-stem>.txt``: a pair's T file when the list names none (one
    scan of a multi-scan file, ``site.e57:2``, is ``site_scan2``)."""
    return f"{cloud_stem(source)}__{cloud_stem(target)}.txt"


def shard(pairs: list[PairEntry], index: int, count: int) -> list[PairEntry]:
    """Every ``count``-th pair starting at ``index`` (0 <= index < count): the shards of one
    list are disjoint and together hold every pair."""
    if not 0 <= index < count:
        raise ValueError(f"shard index must be in [0, {count}), got {index}")
    return pairs[index::count]
