"""The first stages of the register engine for one cloud: read it, measure its scale, choose
its voxel, and extract its features in its local frame.

:class:`Featurizer` holds one feature extractor (the learned encoder with its weights, or
FPFH) and what it measured per cloud array (:mod:`byoc_cli.pipeline.memo`): a cloud's scale,
its local frame and its features at a voxel are computed once while it is among the most
recently used, so that a pair's fallback and a batch's pairs that share a cloud do not
compute them again.
"""

from __future__ import annotations

import os
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

from byoc_cli.pipeline.inputs import as_points, load_weights
from byoc_cli.pipeline.memo import CloudScales, Memo
from byoc_cli.pipeline.results import Features

if TYPE_CHECKING:
    from byoc_cli.pipeline.recipe import RegistrationRecipe
    from byoc_cli.pipeline.scale import CloudScale, VoxelChoice


class Featurizer:
    """The scale and feature stages of a recipe (its ``features``), for many clouds.

    Args:
        recipe: the recipe whose ``features`` say the kind, the weights and the voxel.
        weights: for byoc: a :func:`~byoc_cli.pipeline.inputs.load_weights` result, or a
            path or None for the recipe's (the shipped weights unless it names a file).
        device: ``"cpu"`` or ``"cuda"``.

    Raises:
        WeightsError: the weights cannot be loaded.
    """

    #: clouds whose scale, frame, features and refinement levels are kept
    CACHE = 8

    def __init__(self, recipe: RegistrationRecipe, weights: Any, device: str) -> None:
        self.recipe = recipe
        self.features = recipe.features.kind
        self.device = device
        voxel = recipe.features.voxel
        self.auto_voxel = voxel == "auto"
        if weights is None or isinstance(weights, (str, os.PathLike)):
            weights = recipe.features.weights
        own = None if voxel in ("auto", "own") else voxel
        self.extractor, self.weights_info = make_extractor(recipe, weights, own, device)
        #: the voxel of every cloud when not auto; the reference of the auto choice when auto
        self.voxel_size = float(self.extractor.voxel_size)
        self._scales = CloudScales(self.CACHE, self.measure)
        self._features_memo = Memo(self.CACHE)
        self._frames = Memo(2 * self.CACHE)  # frames and spreads

    @property
    def weights_sha256(self) -> str | None:
        return self.weights_info["sha256"] if self.weights_info else None

    def load(self, cloud: Any, label: str, scale: float | None, **load: Any):
        """``(points (N, 3) float64, name)`` of an array or a file; the unit check runs only
        when neither ``scale`` nor an auto voxel says what the units are."""
        if scale is None and self.auto_voxel:
            scale = 1.0
        return as_points(cloud, label, scale, **load)

    def measure(self, points: np.ndarray, label: str = "cloud", lines: bool = True) -> CloudScale:
        """How ``points (N, 3)`` are sampled: :class:`~byoc_cli.pipeline.scale.CloudScale`
        (``lines``: :func:`~byoc_cli.pipeline.scale.measure`'s; the radius is the
        :meth:`spread`'s, which the cloud's :meth:`frame` reads too).

        Raises:
            RegistrationError: too few distinct points to read a scale from.
        """
        import torch

        from byoc_cli.pipeline.scale import measure

        return measure(torch.from_numpy(points), label, lines, measured=self.spread(points))

    def spread(self, points: np.ndarray):
        """:func:`~byoc_cli.geometry.sampling.spread` of ``points (N, 3)``, computed once per
        array while among the most recently used."""
        from byoc_cli.geometry.sampling import spread

        return self._frames.get(points, "spread", lambda: spread(points))

    def cloud_scale(self, points: np.ndarray, label: str = "cloud", lines: bool = True):
        """:meth:`measure` of ``points (N, 3)``, once per array
        (:meth:`~byoc_cli.pipeline.memo.CloudScales.scale`; ``lines`` False: its scan lines
        not measured, ``line_voxel`` None)."""
        return self._scales.scale(points, label, lines)

    def rough_share(self, points: np.ndarray, voxel_size: float) -> float:
        """:func:`~byoc_cli.geometry.sampling.rough_share` of ``points (N, 3)`` at
        ``voxel_size``, once per array and voxel (:class:`~byoc_cli.pipeline.memo.CloudScales`)."""
        return self._scales.rough(points, voxel_size)

    def remember_scale(self, points: np.ndarray, scale: CloudScale) -> None:
        """Keep ``scale`` (measured elsewhere) as the :meth:`cloud_scale` of ``points``."""
        self._scales.remember(points, scale)

    def voxel_for(self, *scales: CloudScale) -> VoxelChoice:
        """The auto voxel of clouds measured with :meth:`measure` (a pair shares one; FPFH
        sizes clouds whose points crowd near a scanner by their even radius:
        :func:`~byoc_cli.pipeline.scale.size_radius`)."""
        from byoc_cli.pipeline.scale import choose_voxel

        return choose_voxel(tuple(scales), self.voxel_size, even=self.features == "fpfh")

    def choose_voxel(self, *clouds: np.ndarray, label: str = "cloud", labels=None) -> VoxelChoice:
        """The auto voxel of one or two clouds ``(N, 3)`` (a pair shares one); ``label`` (one
        cloud) or ``labels`` (each cloud) name them in errors.

        Raises:
            RegistrationError: a cloud too small or without extent to read a scale from, or
                two clouds too different in size to be in the same units.
        """
        if labels is None:
            labels = [label] if len(clouds) == 1 else ["source", "target"]
        scales = [self.measure(c, name) for c, name in zip(clouds, labels, strict=True)]
        return self.voxel_for(*scales)

    def frame(self, points: np.ndarray):
        """:func:`~byoc_cli.geometry.sampling.local_frame` of ``points (N, 3)``, computed once
        per array while among the most recently used."""
        from byoc_cli.geometry.sampling import local_frame

        return self._frames.get(points, None, lambda: local_frame(points, self.spread(points)))

    def extract(
        self,
        cloud: Any,
        *,
        scale: float | None = None,
        label: str | None = None,
        intrinsics: str | os.PathLike[str] | None = None,
        depth_scale: float | None = None,
        voxel_size: float | None = None,
    ) -> Features:
        """Features of one cloud (an ``(N, 3)`` array in metres, or a file).

        Args:
            cloud: points or a path (read with :func:`~byoc_cli.pipeline.inputs.load_cloud`).
            scale: multiply the coordinates by this first (None: check they look like metres,
                unless the voxel is auto).
            label: how errors name the cloud (default: its path, or ``"cloud"``).
            intrinsics, depth_scale: for depth-image files (depth_scale None: the layout's
                around the file, else 1000; :func:`~byoc_cli.pipeline.inputs.depth_scale_of`).
            voxel_size: this cloud's voxel (a pair's :meth:`choose_voxel`); None: the
                featurizer's, or with ``"auto"`` the choice for this cloud alone.

        Raises:
            InputError, ShapeError: unreadable or malformed input.
            RegistrationError: fewer than 3 voxels, a voxel larger than the cloud, collinear,
                (auto) too few points to read a scale from.
        """
        points, name = self.load(
            cloud, label or "cloud", scale, intrinsics=intrinsics, depth_scale=depth_scale
        )
        refine_voxel = None
        if voxel_size is None and self.auto_voxel:
            choice = self.choose_voxel(points, label=label or name)
            voxel_size, refine_voxel = choice.voxel_size, choice.refine_voxel
        return self.extract_points(points, scale, label or name, voxel_size, refine_voxel)

    def extract_points(
        self,
        points: np.ndarray,
        scale: float | None,
        label: str,
        voxel_size: float | None = None,
        refine_voxel: float | None = None,
        keep: float = 1.0,
    ) -> Features:
        """Features of ``points (N, 3)`` already in metres, at ``voxel_size`` (None: the
        featurizer's), computed in the cloud's local frame (strays left out); ``refine_voxel``:
        the refinement's voxel (None: ``voxel_size``); ``keep``: the share of the points the
        features are computed from (a seeded random subset;
        :attr:`~byoc_cli.pipeline.scale.VoxelChoice.keep`). The refinement runs on all of
        them (``Features.cloud``)."""
        import torch

        from byoc_cli.pipeline.scale import check_radius

        voxel = voxel_size or self.voxel_size
        frame = self.frame(points)
        check_radius(frame.radius, label)
        subset = keep_subset(len(points), keep)
        if frame.inside is not None:  # strays left out
            subset = (
                np.flatnonzero(frame.inside) if subset is None else subset[frame.inside[subset]]
            )
        used = points if subset is None else points[subset]
        used = used - frame.origin if frame.moved else used
        got = self.extractor(torch.from_numpy(used), label=label, voxel_size=voxel)
        index = got.point_index.numpy()
        index = index if subset is None else subset[index]
        return Features(
            points=points[index],
            feats=got.feats.numpy(),
            point_index=index,
            voxel_size=voxel,
            refine_voxel=refine_voxel,
            scale=1.0 if scale is None else float(scale),
            features=self.features,
            weights_sha256=self.weights_sha256,
            cloud=points,
            origin=frame.origin if frame.moved else None,
        )

    def features_at(self, points: np.ndarray, label: str, voxel: tuple) -> Features:
        """:meth:`extract_points` of ``points (N, 3)`` in metres at ``voxel`` (``(voxel_size,
        refine_voxel, keep)``), once per array and voxel while among the most recent."""
        return self._features_memo.get(
            points, voxel, lambda: self.extract_points(points, 1.0, label, *voxel)
        )


def make_extractor(
    recipe: RegistrationRecipe, weights: Any, voxel_size: float | None, device: str
) -> tuple[Any, dict[str, Any] | None]:
    """The extractor of ``recipe.features.kind`` at ``voxel_size`` (None: the weights' voxel,
    or FPFH's reference voxel) and, for byoc, what the report says of its weights.

    Returns:
        ``(extractor, weights_info | None)``; ``weights_info`` holds ``path``, ``sha256``,
        ``architecture``, ``variant`` and ``code_version``.

    The shipped weights (``weights`` None) are checked against their checksum and their
    metadata read here; their tensors are read when the first cloud is encoded, so that a
    process whose pairs FPFH registers alone never builds the encoder.

    Raises:
        WeightsError: the weights cannot be loaded (the shipped ones: their file, checksum or
            metadata).
    """
    from byoc_cli.pipeline.features import ByocExtractor, FpfhExtractor

    if recipe.features.kind == "fpfh":
        return FpfhExtractor(voxel_size or recipe.features.reference_voxel), None
    if weights is None:  # the shipped file: its tensors are read when first needed
        from byoc_cli.pipeline.default_weights import DEFAULT_WEIGHTS, default_weights_metadata

        meta, digest = default_weights_metadata()
        path, encoder = DEFAULT_WEIGHTS, lambda: load_weights(None).encoder
    else:
        loaded = load_weights(weights) if isinstance(weights, (str, os.PathLike)) else weights
        meta, digest, path, encoder = (
            loaded.metadata,
            loaded.file_sha256,
            loaded.path,
            loaded.encoder,
        )
    trained_voxel = float(meta["voxel_size"])
    if voxel_size is not None and abs(voxel_size - trained_voxel) > 1e-9:
        warnings.warn(
            f"--voxel-size {voxel_size:g} differs from the {trained_voxel:g} m the weights "
            "were trained at",
            stacklevel=4,
        )
    info = {
        "path": str(path),
        "sha256": digest,
        "architecture": meta["architecture"],
        "variant": meta["training"]["variant"],
        "code_version": meta["code_version"],
    }
    return ByocExtractor(encoder, voxel_size or trained_voxel, device), info


def keep_subset(n: int, keep: float) -> np.ndarray | None:
    """A sorted random subset of ``range(n)`` of ``round(keep * n)`` indices (at least 1),
    the same for the same ``n`` and ``keep``; None when ``keep >= 1``."""
    import torch

    if keep >= 1.0 or n == 0:
        return None
    generator = torch.Generator().manual_seed(n)
    count = max(1, round(keep * n))
    return torch.randperm(n, generator=generator)[:count].sort().values.numpy()
