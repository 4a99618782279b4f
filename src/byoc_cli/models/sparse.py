"""Sparse 3-D convolution in plain PyTorch (no compiled extension), CPU and CUDA.

A sparse tensor is a set of active sites with one feature row each:

* ``coords (N, 4)`` int64, rows ``[batch, x, y, z]``. At tensor stride ``s`` the spatial
  part is in units of that level's cells: ``x = floor(x_0 / s)`` for a stride-1 site
  ``x_0``. Several clouds share one tensor through the batch column.
* ``feats (N, C)`` float; ``feats[i]`` belongs to ``coords[i]``.

Every sparse tensor derived from one input shares a :class:`CoordinateManager`, which
owns the site sets of every stride and caches each kernel map, so a map is built once per
batch and per stride and reused by all the layers at that stride (submanifold maps per
kernel size, the k2/s2 down-sampling maps and their transposes).

A kernel map lists, for each kernel offset ``k``, pairs ``(in_idx, out_idx)``: output site
``out_idx[p]`` receives ``feats[in_idx[p]] @ weight[k]``. Weights are shaped
``(K, C_in, C_out)``. Offsets of a kernel of odd size ``k`` are ordered like
``torch.cartesian_prod(r, r, r)`` with ``r = arange(-(k // 2), k // 2 + 1)``, i.e. like the
spatial dimensions of ``torch.nn.functional.conv3d``'s weight (cross-correlation: the output
at ``p`` reads the input at ``p + offset``). The eight k2/s2 offsets are the octants
``(dx, dy, dz)`` in ``{0, 1}^3`` ordered ``dx * 4 + dy * 2 + dz``: the coarse site ``q``
reads the fine site ``2 q + (dx, dy, dz)``, as ``conv3d(kernel_size=2, stride=2)`` does, and
the transposed convolution writes back to exactly those fine sites.

The convolution gathers the input rows of one offset into a contiguous block, multiplies
it by that offset's ``(C_in, C_out)`` weight and adds the product into the output rows
(``index_add_``); the centre offset of a submanifold convolution is one dense matmul.
Every multiply-add is a useful one (no zero padding for missing neighbours). Results are
bit-identical from run to run on CPU. Neighbours are found by packing sites into int64 keys
and looking the shifted keys up in a dense table over the bounding box (binary search in
the sorted keys when the box is very large); only half of the offsets are searched, the
other half mirrors them.

On a 2-core CPU a 64 -> 64 3x3x3 convolution on a 19k-voxel surface runs at about 0.55-0.65
of the FLOP rate of a dense matmul of the same size (``benchmarks/sparse_conv.py``). Each
convolution issues about three small ops per offset: on a machine whose cores are busy
with other processes, OpenMP's default busy waiting can turn every parallel region into a
scheduler time slice; ``OMP_WAIT_POLICY=PASSIVE`` or ``torch.set_num_threads(1)`` avoids it.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn
from torch.autograd.function import once_differentiable

from byoc_cli.errors import ShapeError

#: Keys are packed into this many bits (leaves the int64 sign bit and one spare bit free).
_KEY_BITS = 62
#: Number of k2/s2 kernel offsets (octants of a coarse cell).
NUM_OCTANTS = 8
#: Largest odd kernel size of a submanifold convolution.
MAX_KERNEL_SIZE = 7
#: Largest bounding box (in cells) searched through a dense int32 table (64 MiB).
TABLE_MAX_CELLS = 1 << 24


class KernelMap(NamedTuple):
    """Input/output pairs of one sparse convolution, grouped by kernel offset.

    If ``pairs[j] = (k, in_idx, out_idx)`` then, for every ``p``, output site ``out_idx[p]``
    receives ``feats[in_idx[p]] @ weight[k]``. Within one offset the output indices are
    distinct, and so are the input indices. Offsets without pairs are left out.

    Attributes:
        num_offsets: ``K``, the size of the weight's first dimension.
        num_in: number of input sites.
        num_out: number of output sites.
        pairs: tuple of ``(k, in_idx (P_k,) int64, out_idx (P_k,) int64)``.
        identity_offset: offset whose pairs are ``in = out = arange(num_in)`` (the centre
            of a submanifold convolution), kept out of ``pairs`` and computed as one dense
            matmul; ``-1`` when there is none.
    """

    num_offsets: int
    num_in: int
    num_out: int
    pairs: tuple[tuple[int, torch.Tensor, torch.Tensor], ...]
    identity_offset: int

    @property
    def num_pairs(self) -> int:
        """Number of active (input, output) pairs, the centre offset included."""
        centre = self.num_in if self.identity_offset >= 0 else 0
        return centre + sum(int(i.shape[0]) for _, i, _ in self.pairs)

    @property
    def max_block(self) -> int:
        """Largest number of pairs of one offset in :attr:`pairs` (0 when empty)."""
        return max((int(i.shape[0]) for _, i, _ in self.pairs), default=0)


def kernel_offsets(kernel_size: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """Offsets ``(k**3, 3)`` int64 of an odd cubic kernel, in weight order (see module doc)."""
    if kernel_size < 1 or kernel_size % 2 == 0 or kernel_size > MAX_KERNEL_SIZE:
        raise ShapeError(f"kernel_size must be odd, 1 to {MAX_KERNEL_SIZE}, got {kernel_size}")
    r = torch.arange(-(kernel_size // 2), kernel_size // 2 + 1, device=device)
    return torch.cartesian_prod(r, r, r).reshape(-1, 3)


def _check_coords(coords: torch.Tensor) -> None:
    if coords.ndim != 2 or coords.shape[1] != 4:
        raise ShapeError(
            f"coords must have shape (N, 4) [batch, x, y, z], got {tuple(coords.shape)}"
        )
    if coords.dtype != torch.int64:
        raise ShapeError(f"coords must be int64, got {coords.dtype}")


class _KeyPacker:
    """Packs ``[batch, x, y, z]`` rows into unique int64 keys that keep their lexicographic order.

    The spatial box is the sites' bounding box grown by ``pad`` cells on every side, so
    the key of a site shifted by at most ``pad`` cells per axis is ``key + delta`` (linear
    packing) and never collides with the key of another site.
    """

    def __init__(self, coords: torch.Tensor, pad: int = 0) -> None:
        margin = coords.new_tensor([0, pad, pad, pad])
        self.low = coords.min(dim=0).values - margin
        extent = (coords.max(dim=0).values + margin - self.low + 1).tolist()
        if sum(math.log2(e) for e in extent) >= _KEY_BITS:
            raise ShapeError("coordinates span too large a box to pack into int64 keys")
        self.strides = coords.new_tensor(
            [extent[1] * extent[2] * extent[3], extent[2] * extent[3], extent[3], 1]
        )
        self.volume = math.prod(extent)

    def pack(self, coords: torch.Tensor) -> torch.Tensor:
        """``(M,)`` keys of ``coords (M, 4)`` (rows inside the grown box)."""
        return ((coords - self.low) * self.strides).sum(dim=-1)

    def delta(self, offsets: torch.Tensor) -> torch.Tensor:
        """``(K,)`` key change of spatial ``offsets (K, 3)`` (at most ``pad`` per axis)."""
        return (offsets * self.strides[1:]).sum(dim=-1)


class _SiteSet:
    """The sites of one stride and a key -> row look-up for neighbour searches.

    The look-up is a dense table over the grown bounding box when that box has at most
    :data:`TABLE_MAX_CELLS` cells (a surface at 2.5 cm: about 1.3 M cells), else binary
    search in the sorted keys.
    """

    def __init__(self, coords: torch.Tensor) -> None:
        self.coords = coords
        n = coords.shape[0]
        if n == 0:
            return
        self.packer = _KeyPacker(coords, pad=MAX_KERNEL_SIZE // 2)
        self.keys = self.packer.pack(coords)
        rows = torch.arange(n, device=coords.device)
        self.table: torch.Tensor | None = None
        if self.packer.volume <= TABLE_MAX_CELLS:
            self.table = torch.full(
                (self.packer.volume,), -1, dtype=torch.int32, device=coords.device
            )
            self.table[self.keys] = rows.to(torch.int32)
            duplicates = not torch.equal(self.table[self.keys], rows.to(torch.int32))
        else:
            self.sorted_keys, self.order = torch.sort(self.keys)
            duplicates = bool((self.sorted_keys[1:] == self.sorted_keys[:-1]).any())
        if duplicates:
            raise ShapeError("coords contain duplicate sites")

    def lookup(self, query: torch.Tensor) -> torch.Tensor:
        """Row of each key of ``query`` (keys of the grown box), ``-1`` where no site is."""
        if self.table is not None:
            return self.table[query].long()
        pos = torch.searchsorted(self.sorted_keys, query).clamp_max_(self.keys.shape[0] - 1)
        return torch.where(self.sorted_keys[pos] == query, self.order[pos], -1)


class CoordinateManager:
    """Site sets of every stride of one batch of clouds, and a cache of their kernel maps.

    Args:
        coords: ``(N, 4)`` int64 stride-1 sites ``[batch, x, y, z]``, no duplicates.

    Raises:
        ShapeError: wrong shape or dtype, duplicate sites, or a bounding box too large
            for 62-bit keys.
    """

    def __init__(self, coords: torch.Tensor) -> None:
        _check_coords(coords)
        self.device = coords.device
        self._sites: dict[int, _SiteSet] = {1: _SiteSet(coords.contiguous())}
        self._maps: dict[tuple, KernelMap] = {}

    def coords(self, stride: int) -> torch.Tensor:
        """``(N_s, 4)`` sites at ``stride`` (built by down-sampling when first needed)."""
        return self._site_set(stride).coords

    def num_sites(self, stride: int) -> int:
        """Number of sites at ``stride``."""
        return int(self.coords(stride).shape[0])

    def _site_set(self, stride: int) -> _SiteSet:
        if stride not in self._sites:
            if stride < 2 or stride & (stride - 1):
                raise ShapeError(f"stride must be a power of two, got {stride}")
            self.downsample_map(stride // 2)
        return self._sites[stride]

    def submanifold_map(self, stride: int, kernel_size: int) -> KernelMap:
        """Map of a stride-1 convolution of odd ``kernel_size`` on the sites of ``stride``."""
        key = ("sub", stride, kernel_size)
        if key not in self._maps:
            self._maps[key] = self._build_submanifold(stride, kernel_size)
        return self._maps[key]

    def downsample_map(self, stride: int) -> KernelMap:
        """Map of the k2/s2 convolution from the sites of ``stride`` to those of ``2 * stride``."""
        key = ("down", stride)
        if key not in self._maps:
            self._maps[key] = self._build_downsample(stride)
        return self._maps[key]

    def upsample_map(self, stride: int) -> KernelMap:
        """Map of the k2/s2 transposed convolution from ``stride`` back to ``stride // 2``."""
        key = ("up", stride)
        if key not in self._maps:
            down = self.downsample_map(stride // 2)
            pairs = tuple((k, coarse, fine) for k, fine, coarse in down.pairs)
            self._maps[key] = KernelMap(
                NUM_OCTANTS, down.num_out, down.num_in, pairs, identity_offset=-1
            )
        return self._maps[key]

    def _build_submanifold(self, stride: int, kernel_size: int) -> KernelMap:
        sites = self._site_set(stride)
        n = sites.coords.shape[0]
        offsets = kernel_offsets(kernel_size, self.device)
        num_offsets = offsets.shape[0]
        centre = num_offsets // 2
        if n == 0 or centre == 0:
            return KernelMap(num_offsets, n, n, (), centre)
        # look up the first half of the offsets; offset -d mirrors offset d
        query = sites.keys.unsqueeze(0) + sites.packer.delta(offsets[:centre]).unsqueeze(1)
        neighbour = sites.lookup(query)  # (H, N): site i reads row neighbour[k, i] at offset k
        found = neighbour >= 0
        counts = found.sum(dim=1).tolist()
        flat = torch.nonzero(found.view(-1)).squeeze(1)  # k * n + i, increasing
        here = torch.remainder(flat, n).split(counts)
        there = neighbour.view(-1)[flat].split(counts)
        by_offset: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        for k in range(centre):
            if counts[k]:
                # site `here` reads its neighbour `there` = here + d; `there` reads `here` at -d
                by_offset[k] = (there[k], here[k])
                by_offset[num_offsets - 1 - k] = (here[k], there[k])
        pairs = tuple((k, *by_offset[k]) for k in sorted(by_offset))
        return KernelMap(num_offsets, n, n, pairs, centre)

    def _build_downsample(self, stride: int) -> KernelMap:
        fine = self._site_set(stride).coords
        n = fine.shape[0]
        if n == 0:
            self._sites[2 * stride] = _SiteSet(fine)
            return KernelMap(NUM_OCTANTS, 0, 0, (), -1)
        parent = torch.cat([fine[:, :1], torch.div(fine[:, 1:], 2, rounding_mode="floor")], dim=1)
        keys = _KeyPacker(parent).pack(parent)  # sorted keys give sorted coarse sites
        uniq, coarse_idx = torch.unique(keys, sorted=True, return_inverse=True)
        coarse = parent.new_empty(uniq.shape[0], 4)
        coarse[coarse_idx] = parent  # sites ordered by key
        self._sites[2 * stride] = _SiteSet(coarse)
        bits = fine[:, 1:] - 2 * parent[:, 1:]
        octant = bits[:, 0] * 4 + bits[:, 1] * 2 + bits[:, 2]
        order = torch.argsort(octant * uniq.shape[0] + coarse_idx)
        counts = torch.bincount(octant, minlength=NUM_OCTANTS).tolist()
        pairs, start = [], 0
        for k, count in enumerate(counts):
            if count:
                sel = order[start : start + count]
                pairs.append((k, sel, coarse_idx[sel]))
            start += count
        return KernelMap(NUM_OCTANTS, n, int(uniq.shape[0]), tuple(pairs), -1)


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
    for k, in_idx, out_idx in kmap.pairs:
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
