"""The visual encoder used during training (the paper's section 3.1) and point sampling of its map.

The encoder maps an RGB image ``(B, 3, H, W)`` in [-1, 1] to a dense feature map
``(B, 32, H, W)`` whose per-pixel vectors are L2-normalised. :func:`sample_visual_features`
reads the map at the projections of 3-D points (camera frame, OpenCV axes). With
pixel-centre back-projection (``x = (u + 0.5 - cx) z / fx``) each point reads exactly its
own pixel.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from byoc_cli.errors import ShapeError

VISUAL_FEATURE_DIM = 32
VISUAL_WIDTH = 64
VISUAL_NUM_BLOCKS = 4


class BasicBlock(nn.Module):
    """ResNet BasicBlock at constant width, stride 1: conv3-BN-ReLU-conv3-BN + identity, ReLU."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return F.relu(out + x)


class VisualEncoder(nn.Module):
    """Conv3x3 3->64 (no bias), BN, ReLU; four BasicBlocks at 64; conv1x1 64->32 (no bias), BN.

    No down-sampling: the output has the input's resolution. About 0.30 M parameters.

    Args:
        out_dim: output channels (32 in the paper).
        width: channels of the trunk (64).
        num_blocks: BasicBlocks in the trunk (4).
    """

    def __init__(
        self,
        out_dim: int = VISUAL_FEATURE_DIM,
        width: int = VISUAL_WIDTH,
        num_blocks: int = VISUAL_NUM_BLOCKS,
    ) -> None:
        super().__init__()
        self.out_dim = out_dim
        self.stem = nn.Sequential(
            nn.Conv2d(3, width, 3, padding=1, bias=False),
            nn.BatchNorm2d(width),
            nn.ReLU(inplace=True),
        )
        self.blocks = nn.Sequential(*[BasicBlock(width) for _ in range(num_blocks)])
        self.head = nn.Sequential(nn.Conv2d(width, out_dim, 1, bias=False), nn.BatchNorm2d(out_dim))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Dense unit-norm features.

        Args:
            images: ``(B, 3, H, W)`` float, RGB normalised to [-1, 1].

        Returns:
            ``(B, out_dim, H, W)`` float32, L2-normalised over channels.

        Raises:
            ShapeError: ``images`` is not ``(B, 3, H, W)``.
        """
        if images.ndim != 4 or images.shape[1] != 3:
            raise ShapeError(f"images must have shape (B, 3, H, W), got {tuple(images.shape)}")
        x = self.head(self.blocks(self.stem(images)))
        return F.normalize(x.float(), dim=1)


def project_points(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pinhole projection to continuous pixel coordinates.

    Pixel ``(u, v)`` covers ``[u, u + 1) x [v, v + 1)``, so a point back-projected from the
    centre of pixel ``(u, v)`` projects to ``(u + 0.5, v + 0.5)``.

    Args:
        points: ``(N, 3)`` camera-frame points (x right, y down, z forward), z > 0.
        K: ``(3, 3)`` intrinsics.

    Returns:
        ``(N, 2)`` ``(u, v)`` in the points' dtype.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points must have shape (N, 3), got {tuple(points.shape)}")
    if K.shape != (3, 3):
        raise ShapeError(f"K must have shape (3, 3), got {tuple(K.shape)}")
    K = K.to(points.dtype)
    z = points[:, 2].clamp_min(1e-9)
    u = K[0, 0] * points[:, 0] / z + K[0, 2]
    v = K[1, 1] * points[:, 1] / z + K[1, 2]
    return torch.stack([u, v], dim=1)


def sample_visual_features(
    feature_map: torch.Tensor, points: torch.Tensor, K: torch.Tensor
) -> torch.Tensor:
    """Bilinearly sample a feature map at the projections of points (``align_corners=False``).

    Args:
        feature_map: ``(C, H, W)`` features of one image.
        points: ``(N, 3)`` points in that camera's frame.
        K: ``(3, 3)`` intrinsics of the feature map's resolution.

    Returns:
        ``(N, C)`` float32 features (re-normalised to unit length; a point projecting at a
        pixel centre gets exactly that pixel's vector).
    """
    if feature_map.ndim != 3:
        raise ShapeError(f"feature_map must have shape (C, H, W), got {tuple(feature_map.shape)}")
    _, h, w = feature_map.shape
    uv = project_points(points, K).to(feature_map.dtype)
    # align_corners=False: -1 is the left edge of pixel 0, +1 the right edge of pixel W-1
    grid = torch.stack([2.0 * uv[:, 0] / w - 1.0, 2.0 * uv[:, 1] / h - 1.0], dim=1)
    sampled = F.grid_sample(
        feature_map.unsqueeze(0),
        grid.view(1, 1, -1, 2),
        mode="bilinear",
        padding_mode="border",
        align_corners=False,
    )
    return F.normalize(sampled[0, :, 0].transpose(0, 1).float(), dim=1)
