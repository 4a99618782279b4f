"""The gate's visibility check: a passing result must not put one scan's surfaces where the
other scan's sensor saw empty space.

Each cloud is taken as seen from its own origin, as a depth frame, a 3DMatch fragment (the
frame of its first camera) or a laser scan in its scanner's frame is. Under the reported
``T`` the source's points must not lie in front of the surfaces the target's sensor
measured, nor the target's in front of the source's
(:func:`byoc_cli.geometry.visibility.free_space_share`). A pose that fits a few shared
surfaces but sees through the rest of the other scan (a source slid along kitchen cabinets,
a box-shaped cabinet turned onto its other side) puts a share of its points there; a right
pose a few per cent at most. A passing result above :data:`MAX_FREE_SPACE` does not pass
(``byoc register`` exits 3) and the report's ``visibility`` says how much lies where.

It runs on clouds near their origin (a georeferenced cloud's sensor is not at its origin):
where the learned features see the clouds at their own voxel (the Kinect and room scale of
their training, as the retries and the check), and where an auto voxel coarser than their own
sees larger scans (laser-scanned rooms, LiDAR) that look scanned from their origins: each
hides at most :data:`MAX_HIDDEN` of itself seen from there
(:func:`~byoc_cli.geometry.visibility.hidden_share`). Such scans are often handed over out of
their scanner's frame (a project frame, a benchmark's random transform), where the check
would refuse right results; seen from anywhere but its scanner a room hides much of itself
(42 % to 75 % from 5 m away, at most 3.5 % from its scanner, on the simulated rooms of
docs/rooms.md). Objects, which an auto voxel brings up to the features' scale, are left out
(they are often scanned in a frame of their own). ``--no-visibility`` turns it off.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from byoc_cli.pipeline.retries import at_own_voxel

if TYPE_CHECKING:  # numpy stays unloaded for the commands' --help, which reads the constants
    import numpy as np

    from byoc_cli.pipeline.results import Features, Registration

#: a passing result with more than this share of either cloud in the other's free space fails
MAX_FREE_SPACE = 0.09
#: a side (one cloud in the other's free space) judged on fewer points than this says nothing
MIN_SEEN = 100
#: at an auto voxel coarser than the features' own, the check runs only on clouds that each
#: hide at most this share of themselves seen from their origin
#: (:func:`~byoc_cli.geometry.visibility.hidden_share`; the simulated rooms from their
#: scanners 0.003 to 0.036, from 1 m beside them up to 0.26, from 20 m away 0.40 and more)
MAX_HIDDEN = 0.06


def needs_visibility(result: Registration, enabled: bool) -> bool:
    """Whether ``result`` is checked: the check is on, the result passed and came from the
    global path (a result refined from ``--init`` answers to its trust region)."""
    return enabled and result.passed and result.path == "global"


def coarser_voxel(made: Any, feats: Features) -> bool:
    """Whether ``made`` (a :class:`~byoc_cli.pipeline.registrar.Registrar`) extracted ``feats``
    at an auto voxel coarser than the features' own (scans larger than those they were
    trained on)."""
    return made.auto_voxel and feats.voxel_size > made.voxel_size * (1 + 1e-9)


def own_hidden(feats: Features) -> float:
    """:func:`~byoc_cli.geometry.visibility.hidden_share` of ``feats``' kept points at their
    voxel, in input units."""
    import torch

    from byoc_cli.geometry.visibility import hidden_share

    points = torch.as_tensor(feats.points, dtype=torch.float64) / feats.scale
    return hidden_share(points, feats.voxel_size / feats.scale)


def near_origin(feats: Features) -> bool:
    """Whether ``feats``' cloud lies about its own origin (not moved to a local frame as a
    georeferenced cloud is: :func:`byoc_cli.geometry.sampling.local_frame`)."""
    return feats.origin is None or not bool((feats.origin != 0).any())


def free_space(
    src_points: np.ndarray, tgt_points: np.ndarray, T: np.ndarray, voxel_size: float, **image: Any
) -> dict:
    """How much of each cloud lies in the other's free space under ``T``.

    Args:
        src_points, tgt_points: ``(N, 3)``, ``(M, 3)`` each in its sensor's frame, in the
            units of ``T``'s translation.
        T: ``(4, 4)`` ``T_tgt_src``.
        voxel_size: the features' voxel, in the same units.
        image: :func:`~byoc_cli.geometry.visibility.range_image`'s keywords (benchmarks).

    Returns:
        ``source_in_target`` and ``target_in_source`` (shares), ``seen`` (how many points of
        each were judged), ``free_space`` (the larger share among the sides with at least
        :data:`MIN_SEEN` judged points; 0 without one) and ``max_free_space``.
    """
    import numpy as np
    import torch

    from byoc_cli.geometry import apply_transform, invert_transform
    from byoc_cli.geometry.visibility import free_space_share

    T = torch.from_numpy(np.asarray(T, dtype=np.float64))
    src = torch.from_numpy(np.ascontiguousarray(src_points, dtype=np.float64))
    tgt = torch.from_numpy(np.ascontiguousarray(tgt_points, dtype=np.float64))
    src_share, src_seen = free_space_share(apply_transform(T, src), tgt, voxel_size, **image)
    back = apply_transform(invert_transform(T), tgt)
    tgt_share, tgt_seen = free_space_share(back, src, voxel_size, **image)
    sides = [(s, n) for s, n in ((src_share, src_seen), (tgt_share, tgt_seen)) if n >= MIN_SEEN]
    return {
        "source_in_target": src_share,
        "target_in_source": tgt_share,
        "seen": [src_seen, tgt_seen],
        "free_space": max((s for s, _ in sides), default=0.0),
        "max_free_space": MAX_FREE_SPACE,
    }


def with_visibility(
    result: Registration,
    src: Features,
    tgt: Features,
    hidden: list | None = None,
    start: float | None = None,
) -> Registration:
    """``result`` with its ``visibility`` report (:func:`free_space` of the learned features'
    kept points and voxel, in input units, plus ``consistent`` and ``seconds``, and where
    given each cloud's ``hidden`` share with ``max_hidden``); it does not pass when the
    larger share is above :data:`MAX_FREE_SPACE`. ``start``: the ``time.perf_counter()`` the
    seconds count from (None: now)."""
    start = time.perf_counter() if start is None else start
    note = free_space(
        src.points / src.scale,
        tgt.points / tgt.scale,
        result.T_tgt_src,
        src.voxel_size / src.scale,
    )
    consistent = note["free_space"] <= MAX_FREE_SPACE
    if hidden is not None:
        note.update(hidden=hidden, max_hidden=MAX_HIDDEN)
    seconds = time.perf_counter() - start
    note.update(consistent=consistent, seconds=seconds)
    return result._replace(
        passed=result.passed and consistent,
        visibility=note,
        timings={**result.timings, "visibility": seconds},
    )


def seen(made: Any, result: Registration, pair: tuple, recipe: Any) -> Registration:
    """:func:`with_visibility` of ``result``, the registration of ``pair`` (source and target
    :class:`Features` of ``made``, a :class:`~byoc_cli.pipeline.registrar.Registrar`, whose
    recipe is ``recipe``), where it :func:`needs_visibility` and both clouds lie about their
    origin (:func:`near_origin`): at the features' own voxel
    (:func:`~byoc_cli.pipeline.retries.at_own_voxel`), and at a :func:`coarser_voxel` where
    each cloud hides at most :data:`MAX_HIDDEN` of itself (:func:`own_hidden`, timed with
    the check); ``result`` otherwise."""
    src, tgt = pair
    if not needs_visibility(result, recipe.gate.visibility):
        return result
    if not (near_origin(src) and near_origin(tgt)):
        return result
    if at_own_voxel(made, src):
        return with_visibility(result, src, tgt)
    if not coarser_voxel(made, src):
        return result
    start = time.perf_counter()
    hidden = [own_hidden(src), own_hidden(tgt)]
    if max(hidden) > MAX_HIDDEN:
        return result
    return with_visibility(result, src, tgt, hidden, start)
