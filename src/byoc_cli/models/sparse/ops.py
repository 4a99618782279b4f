"""The sparse convolution itself: gather, matmul, scatter-add per kernel offset, autograd.

The input rows of one offset are gathered into a contiguous block, multiplied by that
offset's ``(C_in, C_out)`` weight and added into the output rows (``index_add_``); the centre
offset of a submanifold convolution is one dense matmul. Bit-identical from run to run on CPU.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from byoc_cli.errors import ShapeError
from byoc_cli.models.sparse.maps import KernelMap


def _conv_forward(feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap) -> torch.Tensor:
    c_in, c_out = weight.shape[1], weight.shape[2]
    if kmap.identity_offset >= 0:
        out = torch.mm(feats, weight[kmap.identity_offset])
    else:
        out = feats.new_zeros(kmap.num_out, c_out)
    size = kmap.max_block
    gathered = feats.new_empty(size, c_in)
    product = feats.new_empty(size, c_out)
    for k, in_idx, out_idx in kmap.pairs:
        m = in_idx.shape[0]
        g, y = gathered[:m], product[:m]
        torch.index_select(feats, 0, in_idx, out=g)
        torch.mm(g, weight[k], out=y)
        out.index_add_(0, out_idx, y)
    return out


def _conv_backward(
    grad_out: torch.Tensor,
    feats: torch.Tensor,
    weight: torch.Tensor,
    kmap: KernelMap,
    need_feats: bool,
    need_weight: bool,
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    grad_out = grad_out.contiguous()
    grad_feats = grad_weight = None
    centre = kmap.identity_offset
    if need_feats:
        if centre >= 0:
            grad_feats = torch.mm(grad_out, weight[centre].t())
        else:
            grad_feats = feats.new_zeros(kmap.num_in, weight.shape[1])
    if need_weight:
        grad_weight = torch.zeros_like(weight)
        if centre >= 0:
            torch.mm(feats.t(), grad_out, out=grad_weight[centre])
    for k, in_idx, out_idx in kmap.pairs_by_in if kmap.pairs_by_in is not None else kmap.pairs:
        g_out = grad_out.index_select(0, out_idx)
        if need_weight:
            torch.mm(feats.index_select(0, in_idx).t(), g_out, out=grad_weight[k])
        if need_feats:
            grad_feats.index_add_(0, in_idx, torch.mm(g_out, weight[k].t()))
    return grad_feats, grad_weight


class _SparseConvFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, feats, weight, kmap):
        ctx.kmap = kmap
        ctx.save_for_backward(feats, weight)
        return _conv_forward(feats, weight, kmap)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        feats, weight = ctx.saved_tensors
        need_feats, need_weight, _ = ctx.needs_input_grad
        grad_feats, grad_weight = _conv_backward(
            grad_out, feats, weight, ctx.kmap, need_feats, need_weight
        )
        return grad_feats, grad_weight, None


def sparse_conv(
    feats: torch.Tensor,
    weight: torch.Tensor,
    kmap: KernelMap,
    bias: torch.Tensor | None = None,
) -> torch.Tensor:
    """Sparse convolution of ``feats`` along the pairs of ``kmap``.

    ``out[o] = bias + sum over pairs (k, i, o) of feats[i] @ weight[k]``. Differentiable
    in ``feats``, ``weight`` and ``bias`` (first order). Under ``torch.autocast`` it runs
    in the autocast dtype, like a matmul.

    Args:
        feats: ``(kmap.num_in, C_in)`` float.
        weight: ``(kmap.num_offsets, C_in, C_out)``, same dtype and device.
        kmap: from a :class:`CoordinateManager`.
        bias: optional ``(C_out,)``.

    Returns:
        ``(kmap.num_out, C_out)``.

    Raises:
        ShapeError: shapes that do not fit together.
    """
    if feats.ndim != 2 or feats.shape[0] != kmap.num_in:
        raise ShapeError(f"feats must have shape ({kmap.num_in}, C_in), got {tuple(feats.shape)}")
    if weight.ndim != 3 or weight.shape[0] != kmap.num_offsets or weight.shape[1] != feats.shape[1]:
        raise ShapeError(
            f"weight must have shape ({kmap.num_offsets}, {feats.shape[1]}, C_out), "
            f"got {tuple(weight.shape)}"
        )
    dtype = _autocast_dtype(feats.device.type)
    if dtype is None:
        out = _SparseConvFunction.apply(feats.contiguous(), weight.contiguous(), kmap)
    else:
        # under autocast, run the whole convolution in the autocast dtype (as a matmul would)
        with torch.autocast(feats.device.type, enabled=False):
            out = _SparseConvFunction.apply(
                feats.to(dtype).contiguous(), weight.to(dtype).contiguous(), kmap
            )
    if bias is not None:
        out = out + bias.to(out.dtype)
    return out


def _autocast_dtype(device_type: str) -> torch.dtype | None:
    """The autocast dtype active for ``device_type``, or None."""
    if device_type not in ("cpu", "cuda") or not torch.is_autocast_enabled(device_type):
        return None
    return torch.get_autocast_dtype(device_type)
