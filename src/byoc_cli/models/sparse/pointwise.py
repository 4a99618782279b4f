"""Per-site layers of sparse tensors: batch normalisation over the active sites, ReLU."""

from __future__ import annotations

import warnings

import torch.nn.functional as F
from torch import nn

from byoc_cli.models.sparse.tensor import SparseTensor


class SparseBatchNorm(nn.BatchNorm1d):
    """BatchNorm over the active sites (the rows of ``feats``); parameters as BatchNorm1d.

    In training mode a tensor with fewer than two sites cannot give batch statistics; it
    is normalised with the running statistics instead (not updated), with a warning.
    """

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        feats = x.feats
        if self.training and feats.shape[0] < 2:
            warnings.warn(
                f"SparseBatchNorm on {feats.shape[0]} site(s) in training mode: "
                "using the running statistics",
                RuntimeWarning,
                stacklevel=2,
            )
            out = F.batch_norm(
                feats,
                self.running_mean,
                self.running_var,
                self.weight,
                self.bias,
                False,
                0.0,
                self.eps,
            )
            return x.with_feats(out)
        return x.with_feats(super().forward(feats))


class SparseReLU(nn.Module):
    """ReLU on the features."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_feats(F.relu(x.feats))
