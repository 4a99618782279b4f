"""The sparse tensor: features on the sites of one stride of a coordinate manager."""

from __future__ import annotations

from typing import NamedTuple

import torch

from byoc_cli.errors import ShapeError
from byoc_cli.models.sparse.maps import CoordinateManager


class SparseTensor(NamedTuple):
    """Features on the sites of one stride of a :class:`CoordinateManager`.

    Attributes:
        feats: ``(N, C)`` float; row ``i`` belongs to ``coords[i]``.
        coords: ``(N, 4)`` int64 ``[batch, x, y, z]`` in units of the stride's cells.
        stride: tensor stride (1, 2, 4, ...).
        manager: the shared coordinate manager (site sets and kernel-map cache).
    """

    feats: torch.Tensor
    coords: torch.Tensor
    stride: int
    manager: CoordinateManager

    @classmethod
    def from_coords(cls, coords: torch.Tensor, feats: torch.Tensor) -> SparseTensor:
        """A stride-1 tensor with a new coordinate manager.

        Args:
            coords: ``(N, 4)`` int64 ``[batch, x, y, z]``, no duplicate rows.
            feats: ``(N, C)`` float.

        Raises:
            ShapeError: wrong shapes or dtypes, or duplicate sites.
        """
        manager = CoordinateManager(coords)
        if feats.ndim != 2 or feats.shape[0] != coords.shape[0]:
            raise ShapeError(
                f"feats must have shape ({coords.shape[0]}, C), got {tuple(feats.shape)}"
            )
        return cls(feats, manager.coords(1), 1, manager)

    def with_feats(self, feats: torch.Tensor) -> SparseTensor:
        """The same sites with other features ``(N, C')``."""
        return self._replace(feats=feats)


def sparse_cat(*tensors: SparseTensor) -> SparseTensor:
    """Concatenate the features of sparse tensors on the same sites (same manager, stride)."""
    first = tensors[0]
    for t in tensors[1:]:
        if t.manager is not first.manager or t.stride != first.stride:
            raise ShapeError("sparse_cat needs tensors on the same sites (manager and stride)")
    return first.with_feats(torch.cat([t.feats for t in tensors], dim=1))
