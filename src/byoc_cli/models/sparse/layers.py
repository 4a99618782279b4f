"""Sparse convolution modules: submanifold (stride 1), k2/s2 strided and transposed."""

from __future__ import annotations

import math

import torch
from torch import nn

from byoc_cli.errors import ShapeError
from byoc_cli.models.sparse.maps import NUM_OCTANTS, kernel_offsets
from byoc_cli.models.sparse.ops import sparse_conv
from byoc_cli.models.sparse.tensor import SparseTensor


def _init_conv(weight: torch.Tensor, bias: torch.Tensor | None) -> None:
    # as torch.nn.Conv3d: kaiming_uniform(a=sqrt(5)), i.e. U(+-1/sqrt(fan_in))
    fan_in = weight.shape[0] * weight.shape[1]
    bound = 1.0 / math.sqrt(fan_in) if fan_in > 0 else 0.0
    nn.init.uniform_(weight, -bound, bound)
    if bias is not None:
        nn.init.uniform_(bias, -bound, bound)


class _SparseConvBase(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, num_offsets: int, bias: bool) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.weight = nn.Parameter(torch.empty(num_offsets, in_channels, out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        _init_conv(self.weight, self.bias)

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, bias={self.bias is not None}"


class SubmanifoldConv(_SparseConvBase):
    """Stride-1 sparse convolution: output sites are the input sites.

    Args:
        in_channels, out_channels: feature widths.
        kernel_size: odd cubic kernel size (1 is a per-site linear map).
        bias: add a learned bias.

    ``forward(x: SparseTensor) -> SparseTensor`` on the same sites; weight
    ``(kernel_size**3, in_channels, out_channels)``.
    """

    def __init__(
        self, in_channels: int, out_channels: int, kernel_size: int = 3, bias: bool = False
    ) -> None:
        kernel_offsets(kernel_size)  # validates
        super().__init__(in_channels, out_channels, kernel_size**3, bias)
        self.kernel_size = kernel_size

    def forward(self, x: SparseTensor) -> SparseTensor:
        if self.kernel_size == 1:
            out = torch.mm(x.feats, self.weight[0])
            return x.with_feats(out + self.bias if self.bias is not None else out)
        kmap = x.manager.submanifold_map(x.stride, self.kernel_size)
        return x.with_feats(sparse_conv(x.feats, self.weight, kmap, self.bias))

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, kernel_size={self.kernel_size}"


class StridedConv(_SparseConvBase):
    """Kernel-2 stride-2 sparse convolution onto ``unique(floor(site / 2))`` per batch.

    ``forward(x: SparseTensor) -> SparseTensor`` at stride ``2 * x.stride``; weight
    ``(8, in_channels, out_channels)`` indexed by octant (see the module doc).
    """

    def __init__(self, in_channels: int, out_channels: int, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, NUM_OCTANTS, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        kmap = x.manager.downsample_map(x.stride)
        feats = sparse_conv(x.feats, self.weight, kmap, self.bias)
        stride = 2 * x.stride
        return SparseTensor(feats, x.manager.coords(stride), stride, x.manager)


class TransposedConv(_SparseConvBase):
    """Kernel-2 stride-2 transposed sparse convolution back onto the cached finer sites.

    ``forward(x: SparseTensor) -> SparseTensor`` at stride ``x.stride // 2`` on exactly the
    sites that were down-sampled to ``x``'s (no new sites); weight ``(8, in, out)``.
    """

    def __init__(self, in_channels: int, out_channels: int, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, NUM_OCTANTS, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        if x.stride < 2:
            raise ShapeError("TransposedConv needs a tensor of stride >= 2")
        kmap = x.manager.upsample_map(x.stride)
        feats = sparse_conv(x.feats, self.weight, kmap, self.bias)
        stride = x.stride // 2
        return SparseTensor(feats, x.manager.coords(stride), stride, x.manager)
