"""Site sets and kernel maps of sparse convolutions, built once per batch and stride.

Sites are packed into int64 keys and looked up in a dense table over the bounding box
(binary search in the sorted keys when the box is very large); a submanifold map searches
half of the offsets, the other half mirrors them. Offset order and the map's meaning: see
:mod:`byoc_cli.models.sparse`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

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
        pairs_by_in: the same pairs ordered by input index within each offset (the
            backward pass scatters into the inputs), or None to use :attr:`pairs`. Maps
            built by :class:`CoordinateManager` order :attr:`pairs` by output index and
            fill this field: scatter-adds into ascending rows stay in cache.
    """

    num_offsets: int
    num_in: int
    num_out: int
    pairs: tuple[tuple[int, torch.Tensor, torch.Tensor], ...]
    identity_offset: int
    pairs_by_in: tuple[tuple[int, torch.Tensor, torch.Tensor], ...] | None = None

    @property
    def num_pairs(self) -> int:
        """Number of active (input, output) pairs, the centre offset included."""
        centre = self.num_in if self.identity_offset >= 0 else 0
        return centre + sum(int(i.shape[0]) for _, i, _ in self.pairs)

    @property
    def max_block(self) -> int:
        """Largest number of pairs of one offset in :attr:`pairs` (0 when empty)."""
        return max((int(i.shape[0]) for _, i, _ in self.pairs), default=0)


def _ordered(pairs, column: int) -> tuple[tuple[int, torch.Tensor, torch.Tensor], ...]:
    """``pairs`` with each offset's rows sorted by input (``column`` 1) or output (2)."""
    out = []
    for k, in_idx, out_idx in pairs:
        key = in_idx if column == 1 else out_idx
        if key.numel() > 1 and not bool((key[1:] >= key[:-1]).all()):
            order = torch.argsort(key)
            in_idx, out_idx = in_idx[order], out_idx[order]
        out.append((k, in_idx, out_idx))
    return tuple(out)


def _both_orders(
    num_offsets: int, num_in: int, num_out: int, pairs, identity_offset: int
) -> KernelMap:
    """A :class:`KernelMap` whose pairs are sorted by output, with the by-input copy."""
    return KernelMap(
        num_offsets,
        num_in,
        num_out,
        _ordered(pairs, 2),
        identity_offset,
        _ordered(pairs, 1),
    )


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
            self._maps[key] = _both_orders(NUM_OCTANTS, down.num_out, down.num_in, pairs, -1)
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
        return _both_orders(num_offsets, n, n, pairs, centre)

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
        return _both_orders(NUM_OCTANTS, n, int(uniq.shape[0]), tuple(pairs), -1)
