"""The registration methods compared side by side, and how their features are made.

Method names (``--method``):

``byoc``
    The learned geometric encoder (``--weights``, or the shipped weights), voxel size from
    the weights, with the matching, fit and refinement of ``byoc register``'s recipe for
    learned features (``pipeline.recipe.PRESETS["byoc"]``).
``byoc-random``
    The same pipeline on a seeded random ``compact`` encoder (reported as ``random-init``).
``fpfh-ransac``
    Open3D FPFH at the voxel of ``--fpfh-voxel-size``, with the matching and fit of ``byoc
    register --features fpfh`` (``pipeline.recipe.PRESETS["fpfh"]``).
``fpfh-procrustes``
    The same FPFH features with the paper's matching and fit (``pipeline.recipe.PAPER``:
    the top 200 per direction, randomized Procrustes).
``icp-point`` / ``icp-plane``
    Open3D point-to-point / point-to-plane ICP from the identity on clouds voxelised at
    2.5 cm, correspondences up to :data:`ICP_MAX_DISTANCE` (10 cm), 50 iterations.
``identity``
    ``T = I``: the motion of the pair itself, a floor for every method.

Feature methods use a seeded random subset of ``max_points`` kept points per cloud
(``--num-samples``). A registration that raises (e.g. fewer than 3 correspondences) returns the
identity and is counted as failed.

The feature specs of the methods are made in :mod:`byoc_cli.evaluation.method_features`, the
ICP baselines run in :mod:`byoc_cli.evaluation.icp`; their public names are re-exported here.
"""

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import torch

from byoc_cli.errors import RegistrationError
from byoc_cli.evaluation.icp import (
    ICP_MAX_DISTANCE,
    ICP_MAX_ITERATION,
    ICP_VOXEL_SIZE,
    icp_points,
    open3d_icp,
)
from byoc_cli.evaluation.method_features import (
    DEFAULT_ARCH,
    FeatureSpec,
    byoc_specs,
    feature_specs,
    fpfh_spec,
    random_spec,
    weights_labels,
)
from byoc_cli.evaluation.method_names import METHOD_NAMES, parse_method_names
from byoc_cli.pipeline.features import CloudFeatures
from byoc_cli.pipeline.recipe import PAPER, PRESETS, RegistrationRecipe
from byoc_cli.pipeline.register import (
    RegisterConfig,
    estimate_transform,
    register_config,
)

__all__ = [
    "DEFAULT_ARCH",
    "FPFH_VOXEL_SIZE",
    "ICP_MAX_DISTANCE",
    "ICP_VOXEL_SIZE",
    "METHOD_NAMES",
    "FeatureSpec",
    "Method",
    "MethodOutput",
    "build_methods",
    "feature_specs",
    "icp_points",
    "open3d_icp",
    "parse_method_names",
    "weights_labels",
]

#: FPFH voxel size (m): the fpfh recipe's, as ``byoc register --features fpfh``.
FPFH_VOXEL_SIZE = PRESETS["fpfh"].features.reference_voxel

#: the recipe of each feature method (its matching, fit and refinement; ``max_points`` is
#: the run's)
RECIPES: dict[str, RegistrationRecipe] = {
    "byoc": PRESETS["byoc"],
    "fpfh-ransac": PRESETS["fpfh"],
    "fpfh-procrustes": PAPER,
}


def _config(kind: str, max_points: int) -> RegisterConfig:
    """The settings of feature method ``kind`` with ``max_points`` per cloud (the
    confidence model of the learned features, as before the recipes: the evaluation reads
    no confidence)."""
    recipe = RECIPES[kind].changed(matching__max_points=max_points)
    return dataclasses.replace(register_config(recipe), confidence_model="byoc")


class MethodOutput(NamedTuple):
    """One registration.

    Attributes:
        T_tgt_src: ``(4, 4)`` float64 estimate (identity when ``failed``).
        failed: the method raised; ``error`` says why.
        error: the message, or None.
    """

    T_tgt_src: torch.Tensor
    failed: bool
    error: str | None


@dataclass
class Method:
    """One column of the comparison.

    Attributes:
        name: column label (``byoc``, ``byoc[name]``, ``fpfh-ransac``, ...).
        kind: one of :data:`METHOD_NAMES`.
        features: the feature spec (None for ICP and identity).
        config: registration settings of feature methods (``seed`` is set per pair).
        icp_distance: ICP's correspondence distance (m), ICP methods only.
    """

    name: str
    kind: str
    features: FeatureSpec | None = None
    config: RegisterConfig | None = None
    icp_distance: float | None = None

    @property
    def needs_clouds(self) -> bool:
        """True when :meth:`register` needs the full-resolution clouds (multiscale refinement)."""
        return self.config is not None and self.config.refine == "multiscale"

    def describe(self) -> dict[str, Any]:
        """JSON-able settings of the method."""
        out: dict[str, Any] = {"name": self.name, "kind": self.kind}
        if self.features is not None:
            out["features"] = {"key": self.features.key, **self.features.identity}
            out["features_info"] = self.features.info
        if self.config is not None:
            out["estimator"] = self.config.estimator
            out["num_correspondences_per_direction"] = self.config.num_correspondences
            out["max_points"] = self.config.max_points
            out["refine"] = self.config.refine or "none"
            if self.config.estimator == "procrustes":
                out["num_subsets"] = self.config.num_subsets
                out["subset_size"] = self.config.subset_size
            elif self.config.estimator == "sc2":
                out["inlier_threshold_m"] = self.config.inlier_factor * self.features.voxel_size
            else:
                out["ransac_inlier_threshold_m"] = (
                    self.config.inlier_factor * self.features.voxel_size
                )
                out["ransac_max_iterations"] = self.config.ransac_iterations
                out["ransac_confidence"] = self.config.ransac_confidence
        if self.kind.startswith("icp"):
            out["icp"] = {
                "estimation": "point-to-plane" if self.kind == "icp-plane" else "point-to-point",
                "init": "identity",
                "voxel_size_m": ICP_VOXEL_SIZE,
                "max_correspondence_distance_m": self.icp_distance,
                "max_iteration": ICP_MAX_ITERATION,
            }
        return out

    def register(
        self,
        points_src: torch.Tensor | None,
        points_tgt: torch.Tensor | None,
        feats: tuple[CloudFeatures, CloudFeatures] | None,
        seed: int,
        clouds: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> MethodOutput:
        """Estimate ``T_tgt_src`` for one pair.

        Args:
            points_src, points_tgt: ``(N, 3)`` / ``(M, 3)`` clouds (metres), needed by ICP;
                ICP methods take clouds already voxelised with :func:`icp_points`.
            feats: ``(source, target)`` features, needed by feature methods.
            seed: seeds the subset and the estimator.
            clouds: full-resolution ``(source, target)`` points, for methods that
                :attr:`needs_clouds` (None: they refine on the kept points).

        Returns:
            :class:`MethodOutput`.
        """
        eye = torch.eye(4, dtype=torch.float64)
        try:
            if self.kind == "identity":
                return MethodOutput(eye, False, None)
            if self.kind in ("icp-point", "icp-plane"):
                T = open3d_icp(
                    points_src,
                    points_tgt,
                    eye,
                    self.icp_distance,
                    point_to_plane=self.kind == "icp-plane",
                    max_iteration=ICP_MAX_ITERATION,
                )
                return MethodOutput(T, False, None)
            config = dataclasses.replace(self.config, seed=seed)
            result = estimate_transform(
                feats[0], feats[1], config, self.features.voxel_size, clouds
            )
            return MethodOutput(result.T_tgt_src.to(torch.float64), False, None)
        except RegistrationError as exc:
            return MethodOutput(eye, True, str(exc))


def build_methods(
    names: Sequence[str],
    weights: Sequence[Path] = (),
    *,
    seed: int = 0,
    device: str = "cpu",
    fpfh_voxel_size: float = FPFH_VOXEL_SIZE,
    icp_distance: float = ICP_MAX_DISTANCE,
    max_points: int = PRESETS["byoc"].matching.max_points,
) -> list[Method]:
    """Build the method columns.

    ``byoc`` becomes one column per weights file (``byoc[stem]`` when there are several);
    the FPFH methods share one feature spec.

    Args:
        names: method names (see :data:`METHOD_NAMES`), already parsed.
        weights: weights files for ``byoc`` (at least one when ``byoc`` is named).
        seed: seed of the random encoder of ``byoc-random``.
        device: where the encoder runs.
        fpfh_voxel_size: FPFH voxel size (m).
        icp_distance: ICP correspondence distance (m).
        max_points: points per cloud entering matching.

    Returns:
        The methods in the order of ``names``.

    Raises:
        WeightsError: a weights file is unusable.
        ValueError: an unknown name.
    """
    methods: list[Method] = []
    fpfh: FeatureSpec | None = None
    for name in names:
        if name == "byoc":
            for spec in byoc_specs(weights, seed, device):
                methods.append(Method(spec.key, "byoc", spec, _config("byoc", max_points)))
        elif name == "byoc-random":
            spec = random_spec(seed, device)
            methods.append(Method(spec.key, "byoc", spec, _config("byoc", max_points)))
        elif name in ("fpfh-ransac", "fpfh-procrustes"):
            fpfh = fpfh or fpfh_spec(fpfh_voxel_size)
            methods.append(Method(name, name, fpfh, _config(name, max_points)))
        elif name in ("icp-point", "icp-plane"):
            methods.append(Method(name, name, icp_distance=icp_distance))
        elif name == "identity":
            methods.append(Method(name, name))
        else:
            raise ValueError(f"unknown method {name!r} (known: {', '.join(METHOD_NAMES)})")
    return methods
