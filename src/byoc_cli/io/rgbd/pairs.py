"""Frame pairs of one sequence for training and validation (the paper's section 4, Datasets)."""

from __future__ import annotations


def make_pairs(num_frames: int, spacing: int = 20, mode: str = "train") -> list[tuple[int, int]]:
    """Frame pairs of one sequence (the paper's section 4, Datasets).

    ``"train"``: every frame ``i`` with ``i + spacing`` (all starts). ``"val"``: every
    ``spacing``-th frame, consecutive ones paired: ``(0, s), (s, 2s), ...``.

    Args:
        num_frames: number of (valid) frames of the sequence.
        spacing: frames between the two views, >= 1.
        mode: ``"train"`` or ``"val"``.

    Returns:
        ``[(i, j)]`` with ``j = i + spacing < num_frames``, increasing ``i``; empty when the
        sequence is too short.

    Raises:
        ValueError: ``num_frames < 0``, ``spacing < 1`` or an unknown ``mode``.
    """
    num_frames, spacing = int(num_frames), int(spacing)
    if num_frames < 0:
        raise ValueError(f"num_frames must be >= 0, got {num_frames}")
    if spacing < 1:
        raise ValueError(f"spacing must be >= 1, got {spacing}")
    if mode == "train":
        starts = range(0, max(0, num_frames - spacing))
    elif mode == "val":
        starts = range(0, max(0, num_frames - spacing), spacing)
    else:
        raise ValueError(f"mode must be 'train' or 'val', got {mode!r}")
    return [(i, i + spacing) for i in starts]
