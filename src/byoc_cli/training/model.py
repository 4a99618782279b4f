"""The BYOC training model: visual encoder, geometric encoder and SimSiam predictor.

One forward pass computes the per-sample losses of a batch of :class:`PairSample` s and
returns their batch means. Registration direction: view 1 is the source, view 0 the
target (``T_0_1``). The model never changes its own mode: byoc-rot's augmentation is
applied only when ``self.training`` is true (the authors' implementation gated it on a call
that is always false: docs/training.md).
"""

from __future__ import annotations

import contextlib
from typing import NamedTuple

import torch
from torch import nn

from byoc_cli.geometry import apply_transform, random_rigid_transform, voxelize
from byoc_cli.models.visual import VisualEncoder, sample_visual_features
from byoc_cli.training.config import GEOMETRIC_VARIANTS, VARIANTS, VISUAL_VARIANTS
from byoc_cli.training.data import PairSample
from byoc_cli.training.losses import (
    Predictor,
    geometric_registration_loss,
    register_features,
    transfer_loss,
    visual_registration_loss,
)

#: fewer kept points than this in a view and the sample is left out of the loss
MIN_POINTS = 8


class LossTerms(NamedTuple):
    """Batch means (float32 scalars; zero for the terms a variant does not use).

    Attributes:
        total: ``vis + geo + v2g``.
        vis, geo, v2g: the three terms.
        num_samples: samples that entered the mean.
    """

    total: torch.Tensor
    vis: torch.Tensor
    geo: torch.Tensor
    v2g: torch.Tensor
    num_samples: int


class _Cloud(NamedTuple):
    xyz: torch.Tensor  # (M, 3) float32 kept points (original xyz), camera frame
    coords: torch.Tensor  # (M, 3) int64 voxel coordinates fed to the geometric encoder


class ByocModel(nn.Module):
    """Everything that trains.

    Args:
        variant: ``byoc``, ``byoc-geo``, ``byoc-vis`` or ``byoc-rot``.
        arch: geometric encoder architecture (``byoc_cli.models.encoder.ENCODER_CONFIGS``).
        voxel_size: metres.
        num_correspondences: top-k per direction (200).
        rot_max_angle_deg, rot_max_translation: byoc-rot augmentation ranges.
        augment_seed: seed of the augmentation generator (``self.aug_generator``, CPU).
        amp_dtype: autocast dtype for the encoders on CUDA, or None.
    """

    def __init__(
        self,
        variant: str = "byoc",
        arch: str = "compact",
        voxel_size: float = 0.025,
        num_correspondences: int = 200,
        rot_max_angle_deg: float = 80.0,
        rot_max_translation: float = 0.5,
        augment_seed: int = 0,
        amp_dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        from byoc_cli.models.encoder import build_encoder

        self.variant = variant
        self.arch = arch
        self.voxel_size = float(voxel_size)
        self.k = int(num_correspondences)
        self.rot_max_angle_deg = float(rot_max_angle_deg)
        self.rot_max_translation = float(rot_max_translation)
        self.amp_dtype = amp_dtype
        self.visual = VisualEncoder() if variant in VISUAL_VARIANTS else None
        self.geometric = build_encoder(arch) if variant in GEOMETRIC_VARIANTS else None
        self.predictor = Predictor(32) if variant in ("byoc", "byoc-rot") else None
        self.augment = variant == "byoc-rot"
        self.aug_generator = torch.Generator().manual_seed(int(augment_seed))

    # ------------------------------------------------------------------ helpers
    def _autocast(self, device: torch.device):
        if self.amp_dtype is not None and device.type == "cuda":
            return torch.autocast("cuda", dtype=self.amp_dtype)
        return contextlib.nullcontext()

    def _clouds(self, batch: list[PairSample], device: torch.device) -> list[tuple[_Cloud, _Cloud]]:
        out = []
        for sample in batch:
            views = []
            for v, view in enumerate((sample.view0, sample.view1)):
                points = view.points.to(device)
                if v == 1 and self.augment and self.training:
                    # byoc-rot: move view 1's cloud for the geometric encoder only; the kept
                    # points keep their original xyz for fitting and visual sampling
                    T_aug = random_rigid_transform(
                        self.rot_max_angle_deg, self.rot_max_translation, self.aug_generator
                    ).to(device)
                    grid = voxelize(apply_transform(T_aug, points.double()), self.voxel_size)
                    views.append(_Cloud(points[grid.point_index], grid.coords))
                else:
                    idx = view.point_index.to(device)
                    views.append(_Cloud(points[idx], view.coords.to(device)))
            out.append((views[0], views[1]))
        return out

    def encode_geometric(self, coords: list[torch.Tensor]) -> list[torch.Tensor]:
        """Batched geometric features of several clouds.

        Args:
            coords: ``(M_b, 3)`` int64 voxel coordinates per cloud.

        Returns:
            ``(M_b, 32)`` float32 unit features per cloud.
        """
        device = coords[0].device
        batch_col = torch.cat(
            [
                torch.full((c.shape[0], 1), b, dtype=torch.int64, device=device)
                for b, c in enumerate(coords)
            ]
        )
        coords4 = torch.cat([batch_col, torch.cat(coords)], dim=1)
        ones = torch.ones(coords4.shape[0], 3, dtype=torch.float32, device=device)
        with self._autocast(device):
            feats = self.geometric(coords4, ones)
        return list(feats.float().split([c.shape[0] for c in coords]))

    # ------------------------------------------------------------------ forward
    def forward(self, batch: list[PairSample]) -> LossTerms:
        """Mean losses of a batch (see :class:`LossTerms`)."""
        device = next(self.parameters()).device
        clouds = self._clouds(batch, device)
        valid = [min(c0.xyz.shape[0], c1.xyz.shape[0]) >= MIN_POINTS for c0, c1 in clouds]

        geo_feats: list[torch.Tensor] | None = None
        if self.geometric is not None:
            coords = [c.coords for pair in clouds for c in pair]
            geo_feats = self.encode_geometric(coords)

        vis_feats: list[torch.Tensor] | None = None
        if self.visual is not None:
            images = torch.stack([img for s in batch for img in (s.view0.color, s.view1.color)])
            with self._autocast(device):
                maps = self.visual(images.to(device))
            maps = maps.float()
            vis_feats = []
            for b, (c0, c1) in enumerate(clouds):
                for v, cloud in enumerate((c0, c1)):
                    K = (batch[b].view0 if v == 0 else batch[b].view1).K.to(device)
                    vis_feats.append(sample_visual_features(maps[2 * b + v], cloud.xyz, K))

        zero = torch.zeros((), dtype=torch.float64, device=device)
        sums = {"vis": zero, "geo": zero, "v2g": zero}
        n = 0
        for b, (c0, c1) in enumerate(clouds):
            if not valid[b]:
                continue
            n += 1
            vis_reg = None
            if vis_feats is not None:
                # source = view 1, target = view 0
                vis_reg = register_features(
                    vis_feats[2 * b + 1], vis_feats[2 * b], c1.xyz, c0.xyz, self.k
                )
                sums["vis"] = sums["vis"] + visual_registration_loss(
                    vis_reg.T_tgt_src, vis_reg.points_src, vis_reg.points_tgt, vis_reg.weight
                )
            if geo_feats is not None:
                g0, g1 = geo_feats[2 * b], geo_feats[2 * b + 1]
                geo_reg = register_features(g1, g0, c1.xyz, c0.xyz, self.k)
                sums["geo"] = sums["geo"] + geometric_registration_loss(
                    geo_reg.T_tgt_src, geo_reg.points_src, geo_reg.points_tgt
                )
                if self.predictor is not None and vis_reg is not None:
                    # the visual correspondences index the geometric features; integer
                    # indices carry no gradient to the visual encoder
                    sums["v2g"] = (
                        sums["v2g"]
                        + transfer_loss(
                            g0[vis_reg.tgt_idx], g1[vis_reg.src_idx], self.predictor
                        ).double()
                    )
        denom = max(n, 1)
        vis, geo, v2g = (sums[k].float() / denom for k in ("vis", "geo", "v2g"))
        if n == 0:
            # keep the graph connected so that DDP and backward still work
            anchor = sum(p.sum() for p in self.parameters()) * 0.0
            vis, geo, v2g = vis + anchor, geo + anchor, v2g + anchor
        return LossTerms(vis + geo + v2g, vis, geo, v2g, n)
