"""Sparse UNet geometric encoders, by name.

The encoder turns the occupied voxels of a cloud into one L2-normalised feature per
voxel (the paper's section 3.1). Input: ``coords (N, 4)`` int64 rows ``[batch, x, y, z]``
(voxel indices at stride 1, several clouds told apart by the batch column) and
``feats (N, in_channels)`` float32 (constant ones in the pipeline). Output: ``(N, out_dim)``
unit rows, row ``i`` describing ``coords[i]``.

Layout of a network with ``S`` stages (all convolutions without bias but the last):

* stem: submanifold conv ``stem_kernel`` ``in_channels -> stem_channels``, BN, ReLU;
* encoder stage ``i``: k2/s2 conv (keeps the width), BN, ReLU, then
  ``encoder_blocks[i]`` BasicBlocks to ``encoder_channels[i]``;
* decoder stage ``i``: k2/s2 transposed conv to ``decoder_channels[i]`` onto the finer
  sites, BN, ReLU, concatenation of the encoder's output at that stride (the stem's for
  the last stage), then ``decoder_blocks[i]`` BasicBlocks to ``decoder_channels[i]``;
* final submanifold conv k1 to ``out_dim`` with bias, then L2 normalisation.

A BasicBlock is conv-BN-ReLU-conv-BN plus a shortcut (identity, or k1 conv + BN when the
width changes), then ReLU. ``minkunet34c`` is MinkowskiEngine's MinkUNet34C as the BYOC
research code uses it (about 37.9 M parameters); ``compact`` is the CPU default.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from byoc_cli.errors import ShapeError
from byoc_cli.models.sparse import (
    SparseBatchNorm,
    SparseReLU,
    SparseTensor,
    StridedConv,
    SubmanifoldConv,
    TransposedConv,
    sparse_cat,
)

#: Small constant of the final L2 normalisation.
NORM_EPS = 1e-12


@dataclass(frozen=True)
class EncoderConfig:
    """Architecture of a :class:`GeometricEncoder` (serialisable with ``dataclasses.asdict``).

    Attributes:
        name: registry name (``compact``, ``minkunet34c``) or a custom label.
        in_channels: input feature width (3: the pipeline feeds ones).
        out_dim: output feature width.
        stem_channels: width of the stem (stride 1) and of its skip connection.
        stem_kernel: odd kernel size of the stem convolution.
        block_kernel: odd kernel size of the convolutions inside the BasicBlocks.
        encoder_channels: width of each encoder stage (strides 2, 4, 8, ...).
        encoder_blocks: BasicBlocks per encoder stage (each >= 1).
        decoder_channels: width of each decoder stage (coarse to fine).
        decoder_blocks: BasicBlocks per decoder stage (each >= 0).
    """

    name: str
    in_channels: int = 3
    out_dim: int = 32
    stem_channels: int = 32
    stem_kernel: int = 5
    block_kernel: int = 3
    encoder_channels: tuple[int, ...] = (32, 64, 128, 256)
    encoder_blocks: tuple[int, ...] = (2, 3, 4, 6)
    decoder_channels: tuple[int, ...] = (256, 128, 96, 96)
    decoder_blocks: tuple[int, ...] = (2, 2, 2, 2)

    def __post_init__(self) -> None:
        # JSON gives lists back: store tuples so that configs compare and hash
        for field in ("encoder_channels", "encoder_blocks", "decoder_channels", "decoder_blocks"):
            object.__setattr__(self, field, tuple(int(v) for v in getattr(self, field)))
        stages = len(self.encoder_channels)
        lengths = {
            len(self.encoder_blocks),
            len(self.decoder_channels),
            len(self.decoder_blocks),
            stages,
        }
        if len(lengths) != 1 or stages < 1:
            raise ValueError("encoder/decoder channels and blocks need one entry per stage (>= 1)")
        widths = (
            self.in_channels,
            self.out_dim,
            self.stem_channels,
            *self.encoder_channels,
            *self.decoder_channels,
        )
        if any(w < 1 for w in widths):
            raise ValueError("all widths must be >= 1")
        if any(b < 1 for b in self.encoder_blocks) or any(b < 0 for b in self.decoder_blocks):
            raise ValueError("encoder stages need >= 1 block, decoder stages >= 0")
        for kernel in (self.stem_kernel, self.block_kernel):
            if kernel < 1 or kernel % 2 == 0:
                raise ValueError(f"kernel sizes must be odd and >= 1, got {kernel}")

    @property
    def num_stages(self) -> int:
        """Number of down-sampling stages (the coarsest stride is ``2 ** num_stages``)."""
        return len(self.encoder_channels)


ENCODER_CONFIGS: dict[str, EncoderConfig] = {
    # MinkUNet34C (MinkowskiEngine), the BYOC research configuration: 37.85 M parameters
    "minkunet34c": EncoderConfig(name="minkunet34c"),
    # CPU default (6.52 M parameters), FCGF-like: one BasicBlock per level, 32 channels
    # at full resolution, widths doubling to 256 at stride 16, no block at stride 1 in the
    # decoder, k3 stem. Chosen by measurement (benchmarks/sparse_conv.py): a k5 stem or a
    # stride-1 decoder block each cost about 40 % more time; the channel widths at the
    # coarse strides are nearly free (few sites there).
    "compact": EncoderConfig(
        name="compact",
        stem_channels=32,
        stem_kernel=3,
        encoder_channels=(32, 64, 128, 256),
        encoder_blocks=(1, 1, 1, 1),
        decoder_channels=(128, 96, 64, 32),
        decoder_blocks=(1, 1, 1, 0),
    ),
}


class ConvBNReLU(nn.Module):
    """A sparse convolution (submanifold, strided or transposed), BatchNorm, ReLU."""

    def __init__(self, conv: nn.Module, channels: int) -> None:
        super().__init__()
        self.conv = conv
        self.bn = SparseBatchNorm(channels)
        self.relu = SparseReLU()

    def forward(self, x: SparseTensor) -> SparseTensor:
        return self.relu(self.bn(self.conv(x)))


class BasicBlock(nn.Module):
    """ResNet BasicBlock on a sparse tensor (submanifold convolutions).

    Parameters: ``conv1``, ``bn1``, ``conv2``, ``bn2`` and, when the width changes,
    ``shortcut.0`` (k1 conv) and ``shortcut.1`` (BN).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3) -> None:
        super().__init__()
        self.conv1 = SubmanifoldConv(in_channels, out_channels, kernel_size)
        self.bn1 = SparseBatchNorm(out_channels)
        self.conv2 = SubmanifoldConv(out_channels, out_channels, kernel_size)
        self.bn2 = SparseBatchNorm(out_channels)
        self.relu = SparseReLU()
        self.shortcut: nn.Module | None = None
        if in_channels != out_channels:
            self.shortcut = nn.Sequential(
                SubmanifoldConv(in_channels, out_channels, kernel_size=1),
                SparseBatchNorm(out_channels),
            )

    def forward(self, x: SparseTensor) -> SparseTensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        residual = x if self.shortcut is None else self.shortcut(x)
        return out.with_feats(F.relu(out.feats + residual.feats))


def _blocks(in_channels: int, out_channels: int, count: int, kernel_size: int) -> nn.Sequential:
    layers = []
    for i in range(count):
        layers.append(
            BasicBlock(in_channels if i == 0 else out_channels, out_channels, kernel_size)
        )
    return nn.Sequential(*layers)


class GeometricEncoder(nn.Module):
    """Sparse UNet that maps occupied voxels to unit feature vectors.

    Args:
        config: the architecture.

    Parameter names (stable, they are the keys of weights files): ``stem.*``,
    ``down.{i}.*`` and ``enc.{i}.{j}.*`` (encoder stage ``i``, block ``j``), ``up.{i}.*``
    and ``dec.{i}.{j}.*`` (decoder stage ``i``, coarse to fine), ``final.weight``,
    ``final.bias``.
    """

    def __init__(self, config: EncoderConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        self.stem = ConvBNReLU(
            SubmanifoldConv(c.in_channels, c.stem_channels, c.stem_kernel), c.stem_channels
        )
        self.down = nn.ModuleList()
        self.enc = nn.ModuleList()
        skips = [c.stem_channels]
        width = c.stem_channels
        for channels, count in zip(c.encoder_channels, c.encoder_blocks, strict=True):
            self.down.append(ConvBNReLU(StridedConv(width, width), width))
            self.enc.append(_blocks(width, channels, count, c.block_kernel))
            width = channels
            skips.append(width)
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        for i, (channels, count) in enumerate(
            zip(c.decoder_channels, c.decoder_blocks, strict=True)
        ):
            self.up.append(ConvBNReLU(TransposedConv(width, channels), channels))
            width = channels + skips[-2 - i]
            self.dec.append(_blocks(width, channels, count, c.block_kernel))
            width = channels if count else width
        self.final = SubmanifoldConv(width, c.out_dim, kernel_size=1, bias=True)

    def forward_sparse(self, x: SparseTensor) -> SparseTensor:
        """The network on a stride-1 sparse tensor; returns unit features on the same sites."""
        out = self.stem(x)
        skips = [out]
        for down, enc in zip(self.down, self.enc, strict=True):
            out = enc(down(out))
            skips.append(out)
        for i, (up, dec) in enumerate(zip(self.up, self.dec, strict=True)):
            out = dec(sparse_cat(up(out), skips[-2 - i]))
        out = self.final(out)
        return out.with_feats(F.normalize(out.feats, dim=1, eps=NORM_EPS))

    def forward(self, coords: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Unit features of the sites of ``coords``.

        Args:
            coords: ``(N, 4)`` int64 ``[batch, x, y, z]`` voxel indices, no duplicate rows.
            feats: ``(N, in_channels)`` float32 input features, same device.

        Returns:
            ``(N, out_dim)`` float32 L2-normalised; row ``i`` belongs to ``coords[i]``.

        Raises:
            ShapeError: wrong shapes or dtypes, duplicate sites.
        """
        if feats.ndim != 2 or feats.shape[1] != self.config.in_channels:
            raise ShapeError(
                f"feats must have shape (N, {self.config.in_channels}), got {tuple(feats.shape)}"
            )
        return self.forward_sparse(SparseTensor.from_coords(coords, feats)).feats


def build_encoder(arch: str, **overrides) -> GeometricEncoder:
    """A randomly initialised encoder of a registered architecture.

    Args:
        arch: a key of :data:`ENCODER_CONFIGS`.
        **overrides: fields of :class:`EncoderConfig` to change (e.g. ``out_dim=16``).

    Returns:
        The encoder (training mode, CPU, initialised from the global torch RNG).

    Raises:
        ValueError: unknown architecture or invalid overrides.
    """
    if arch not in ENCODER_CONFIGS:
        raise ValueError(f"unknown encoder {arch!r}; known: {', '.join(sorted(ENCODER_CONFIGS))}")
    try:
        config = dataclasses.replace(ENCODER_CONFIGS[arch], **overrides)
    except TypeError as exc:
        raise ValueError(f"invalid override for {arch!r}: {exc}") from exc
    return GeometricEncoder(config)


def encode_voxels(encoder: GeometricEncoder, coords: torch.Tensor) -> torch.Tensor:
    """Features of one cloud's voxels (batch 0, constant-ones input features).

    Args:
        encoder: a :class:`GeometricEncoder` on the device of ``coords``.
        coords: ``(M, 3)`` int64 distinct voxel indices (``byoc_cli.geometry.voxelize``).

    Returns:
        ``(M, out_dim)`` unit features, row ``m`` for ``coords[m]``.

    Raises:
        ShapeError: wrong shape or dtype, duplicate voxels.
    """
    if coords.ndim != 2 or coords.shape[1] != 3:
        raise ShapeError(f"coords must have shape (M, 3), got {tuple(coords.shape)}")
    batch = coords.new_zeros(coords.shape[0], 1)
    dtype = next(encoder.parameters()).dtype
    feats = torch.ones(
        coords.shape[0], encoder.config.in_channels, dtype=dtype, device=coords.device
    )
    return encoder(torch.cat([batch, coords], dim=1), feats)
