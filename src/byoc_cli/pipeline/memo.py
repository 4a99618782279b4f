"""What the register engine keeps between pairs, and how it waits for its workers.

A cloud is told by the identity of its ``(N, 3)`` array: the engine reads every array itself
and never changes it, so the work done on it (its scale, its features at a voxel, its local
frame, its refinement levels) is done once while the array is among the most recently used.
A memo holds the array with its value, so that its ``id`` is not reused meanwhile.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from concurrent.futures import Future, wait
from typing import Any

import numpy as np


class Memo:
    """Values of ``(array, key)`` computed once while among the ``size`` most recently used
    (least recently used dropped first). A thread asking for a value another thread computes
    waits for it; a failure is not kept."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict[tuple[int, Any], tuple[np.ndarray, Future]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, array: np.ndarray, key: Any, compute) -> Any:
        """The value of ``(array, key)``; ``compute()`` makes it on a miss."""
        item = (id(array), key)
        with self._lock:
            hit = self._items.get(item)
            if hit is not None and hit[0] is array:
                self._items.move_to_end(item)
                future = hit[1]
            else:
                future, mine = None, Future()
                self._items[item] = (array, mine)
                self._items.move_to_end(item)
                while len(self._items) > self.size:
                    self._items.popitem(last=False)
        if future is not None:
            return future.result()
        try:
            value = compute()
        except BaseException as exc:
            mine.set_exception(exc)
            with self._lock:
                if self._items.get(item, (None, None))[1] is mine:
                    del self._items[item]
            raise
        mine.set_result(value)
        return value


class CloudScales:
    """The measurements of the ``size`` most recently measured clouds, each made once per
    array: its scale (``measure(points, label, lines=False)``, a
    :class:`~byoc_cli.pipeline.scale.CloudScale` without its scan lines), its scan lines
    (:func:`~byoc_cli.pipeline.scale.scan_line_voxel`, measured only when asked for: a
    registration from an initial pose needs no feature voxel) and its roughness at a voxel
    (:func:`~byoc_cli.geometry.sampling.rough_share`)."""

    def __init__(self, size: int, measure) -> None:
        self._memo = Memo(3 * size)
        self._measure = measure

    def scale(self, points: np.ndarray, label: str, lines: bool = True) -> Any:
        """The ``CloudScale`` of ``points (N, 3)`` named ``label``; ``lines`` False: its
        ``line_voxel`` None unless measured before."""
        import torch

        from byoc_cli.pipeline.scale import scan_line_voxel

        base = self._memo.get(points, None, lambda: self._measure(points, label, lines=False))
        if not lines:
            return base._replace(label=label)
        line_voxel = self._memo.get(
            points,
            "lines",
            lambda: scan_line_voxel(torch.from_numpy(points), base.spacing, base.radius),
        )
        return base._replace(label=label, line_voxel=line_voxel)

    def rough(self, points: np.ndarray, voxel_size: float) -> float:
        """The rough share of ``points (N, 3)`` at ``voxel_size``."""
        import torch

        from byoc_cli.geometry.sampling import rough_share

        return self._memo.get(
            points, ("rough", voxel_size), lambda: rough_share(torch.from_numpy(points), voxel_size)
        )

    def remember(self, points: np.ndarray, scale: Any) -> None:
        """Keep ``scale`` (a full ``CloudScale`` measured elsewhere) as that of ``points``."""
        self._memo.get(points, None, lambda: scale._replace(line_voxel=None))
        if scale.line_voxel is not None:
            self._memo.get(points, "lines", lambda: scale.line_voxel)


class RefineClouds:
    """The :class:`~byoc_cli.pipeline.refine_levels.RefineCloud` of the ``size`` most recently
    refined clouds: a cloud refined in several pairs (``register-batch``) builds its levels,
    normals and search index once."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._clouds: OrderedDict[int, tuple[np.ndarray, Any]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, cloud: np.ndarray, voxel: float, local, pyramid: bool = False) -> Any:
        """The refinement cloud of ``cloud (N, 3)`` at ``voxel``; on a miss it is made from
        ``local()``, the cloud in its local frame (its levels are built on use; ``pyramid``:
        see :class:`~byoc_cli.pipeline.refine_levels.RefineCloud`)."""
        from byoc_cli.pipeline.refine_levels import RefineCloud

        key = id(cloud)
        with self._lock:
            hit = self._clouds.get(key)
            if hit is not None and hit[0] is cloud and hit[1].voxel_size == voxel:
                self._clouds.move_to_end(key)
                return hit[1]
            prepared = RefineCloud(local(), voxel, pyramid=pyramid)
            self._clouds[key] = (cloud, prepared)  # holds the array: its id stays its own
            while len(self._clouds) > self.size:
                self._clouds.popitem(last=False)
            return prepared


def all_done(jobs: list[Future]) -> list[Future]:
    """``jobs``, once every one of them has ended: a cloud that fails to load must not leave
    the other one loading on a worker after the pair has raised (its numpy work beside the
    caller's next call deadlocked OpenBLAS in a test run)."""
    wait(jobs)
    return jobs


class InPlace:
    """:meth:`submit` runs the call at once (inside a worker, where waiting for the pool
    could wait for oneself)."""

    def submit(self, fn, *args: Any, **kwargs: Any) -> Future:
        future: Future = Future()
        future.set_result(fn(*args, **kwargs))
        return future
