"""The ground-truth pairs of a 3DMatch-layout benchmark, checked against the fragments."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from byoc_cli.errors import DatasetError
from byoc_cli.io.threedmatch import (
    BenchmarkScene,
    fragment_path,
    read_gt_info,
    read_gt_log,
    read_gt_overlap,
)


class BenchmarkPair(NamedTuple):
    """One ground-truth pair.

    Attributes:
        scene: scene name.
        i: target fragment; j: source fragment.
        T_gt: ``(4, 4)`` float64, maps fragment ``j`` into fragment ``i``.
        info: ``(6, 6)`` information matrix, or None when ``gt.info`` lacks the pair.
        overlap: from ``gt_overlap.log``, or None.
        source, target: the fragment files.
    """

    scene: str
    i: int
    j: int
    T_gt: np.ndarray
    info: np.ndarray | None
    overlap: float | None
    source: Path
    target: Path


class PairSet(NamedTuple):
    """Pairs selected for evaluation.

    Attributes:
        pairs: the pairs to evaluate, scene by scene in ``gt.log`` order.
        scenes: the scenes used.
        num_listed: pairs listed by the selected scenes' ``gt.log`` (before ``limit``).
        missing_fragments: fragment files named by ``gt.log`` but absent (``allow_missing``).
        skipped_pairs: ``(scene, i, j)`` left out because a fragment is missing.
    """

    pairs: list[BenchmarkPair]
    scenes: list[BenchmarkScene]
    num_listed: int
    missing_fragments: list[str]
    skipped_pairs: list[tuple[str, int, int]]


def load_benchmark_pairs(
    scenes: Sequence[BenchmarkScene], limit: int | None = None, allow_missing: bool = False
) -> PairSet:
    """Read the ground truth of ``scenes`` and check that the fragments exist.

    Args:
        scenes: from :func:`byoc_cli.io.threedmatch.discover_benchmark`.
        limit: at most this many pairs per scene (the first ones of ``gt.log``).
        allow_missing: skip pairs whose fragment is missing instead of raising.

    Returns:
        :class:`PairSet`.

    Raises:
        InputError: a malformed ``gt.log``, ``gt.info`` or ``gt_overlap.log``.
        DatasetError: a fragment named by ``gt.log`` is missing (without ``allow_missing``);
            the message names the fragment and the ``gt.log`` line.
    """
    pairs: list[BenchmarkPair] = []
    missing: list[str] = []
    skipped: list[tuple[str, int, int]] = []
    listed = 0
    for scene in scenes:
        records = read_gt_log(scene.gt_log)
        listed += len(records)
        infos = {}
        if scene.gt_info is not None:
            infos = {(r.i, r.j): r.info for r in read_gt_info(scene.gt_info)}
        overlaps = read_gt_overlap(scene.gt_overlap) if scene.gt_overlap is not None else {}
        if limit is not None:
            records = records[:limit]
        for rec in records:
            source, target = fragment_path(scene, rec.j), fragment_path(scene, rec.i)
            absent = [p for p in (target, source) if not p.is_file()]
            if absent:
                if not allow_missing:
                    raise DatasetError(
                        absent[0],
                        f"fragment not found (named by {scene.gt_log} line {rec.line}, pair "
                        f"{rec.i} {rec.j}); pass --allow-missing to skip such pairs",
                    )
                missing += [str(p) for p in absent if str(p) not in missing]
                skipped.append((scene.name, rec.i, rec.j))
                continue
            pairs.append(
                BenchmarkPair(
                    scene.name,
                    rec.i,
                    rec.j,
                    rec.T_tgt_src,
                    infos.get((rec.i, rec.j)),
                    overlaps.get((rec.i, rec.j)),
                    source,
                    target,
                )
            )
    return PairSet(pairs, list(scenes), listed, missing, skipped)
