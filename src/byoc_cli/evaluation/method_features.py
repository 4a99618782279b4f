"""The features of the compared methods: a :class:`FeatureSpec` (extractor and identity) per
weights file of ``byoc``, for the random encoder of ``byoc-random`` and for FPFH; the short
column labels of weights files.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from byoc_cli.pipeline.features import FeatureExtractor

if TYPE_CHECKING:
    from byoc_cli.evaluation.methods import Method

__all__ = [
    "DEFAULT_ARCH",
    "FeatureSpec",
    "byoc_specs",
    "feature_specs",
    "fpfh_spec",
    "random_spec",
    "weights_labels",
]

#: Architecture of the random encoder used for ``byoc`` without weights.
DEFAULT_ARCH = "compact"


@dataclass
class FeatureSpec:
    """A feature extractor and its identity (for the cache and the report).

    Attributes:
        key: short unique label within a run (``byoc``, ``byoc[name]``, ``fpfh``).
        extractor: computes :class:`CloudFeatures` from ``points (N, 3)``.
        identity: JSON-able settings that determine the features (extractor name, voxel
            size, weights hash, radii).
        info: JSON-able description for the report (weights file, source).
    """

    key: str
    extractor: FeatureExtractor
    identity: dict[str, Any]
    info: dict[str, Any]

    @property
    def voxel_size(self) -> float:
        """The extractor's voxel size (m)."""
        return float(self.extractor.voxel_size)


def weights_labels(weights: Sequence[str | Path]) -> list[str]:
    """Short unique column labels for weights files, in order.

    The file stem where it is unique; else ``folder/stem`` (training writes
    ``RUN/weights.safetensors``, so runs are told apart by their folder); else
    ``stem#N`` with N the 1-based position.
    """
    paths = [Path(w) for w in weights]
    stems = [p.stem for p in paths]
    named = [f"{p.parent.name}/{p.stem}" if p.parent.name else p.stem for p in paths]
    labels = []
    for index, stem in enumerate(stems):
        if stems.count(stem) == 1:
            labels.append(stem)
        elif named.count(named[index]) == 1:
            labels.append(named[index])
        else:
            labels.append(f"{stem}#{index + 1}")
    return labels


def random_spec(seed: int, device: str) -> FeatureSpec:
    """``byoc-random``: a randomly initialised encoder, asked for by name."""
    from byoc_cli.pipeline.features import ByocExtractor
    from byoc_cli.pipeline.weights import init_weights, tensors_sha256

    encoder, meta = init_weights(DEFAULT_ARCH, seed)
    digest = tensors_sha256(
        {k: v.detach().cpu().contiguous() for k, v in encoder.state_dict().items()}
    )
    voxel = float(meta["voxel_size"])
    return FeatureSpec(
        key="byoc-random",
        extractor=ByocExtractor(encoder, voxel, device),
        identity={
            "extractor": "byoc",
            "voxel_size": voxel,
            "weights": "random-init",
            "architecture": DEFAULT_ARCH,
            "tensors_sha256": digest,
        },
        info={
            "source": "random-init",
            "note": f"a random {DEFAULT_ARCH} encoder seeded with {seed} "
            "(random geometric features, not trained ones)",
            "architecture": DEFAULT_ARCH,
            "seed": seed,
        },
    )


def byoc_specs(weights: Sequence[Path], seed: int, device: str) -> list[FeatureSpec]:
    """``byoc``: one spec per weights file, keyed ``byoc`` (one file) or ``byoc[label]`` (see
    :func:`weights_labels`); the shipped weights are loaded as the package loads them.

    Args:
        weights: weights files, at least one.
        seed: unused (the learned encoders are not seeded).
        device: where the encoders run.

    Raises:
        ValueError: no weights file.
        WeightsError: a weights file is unusable.
    """
    from byoc_cli.pipeline.features import ByocExtractor
    from byoc_cli.pipeline.weights import load_weights

    del seed
    if not weights:
        raise ValueError("method byoc needs weights (or use byoc-random for a random encoder)")
    from byoc_cli.pipeline.default_weights import default_weights_path, load_default_weights

    shipped = default_weights_path()
    labels = weights_labels(weights)
    specs = []
    for index, path in enumerate(weights):
        is_shipped = shipped is not None and Path(path).resolve() == shipped.resolve()
        loaded = load_default_weights() if is_shipped else load_weights(path)
        voxel = float(loaded.metadata["voxel_size"])
        label = labels[index]
        specs.append(
            FeatureSpec(
                key="byoc" if len(weights) == 1 else f"byoc[{label}]",
                extractor=ByocExtractor(loaded.encoder, voxel, device),
                identity={
                    "extractor": "byoc",
                    "voxel_size": voxel,
                    "weights": "file",
                    "architecture": loaded.metadata["architecture"],
                    "tensors_sha256": loaded.metadata["tensors_sha256"],
                },
                info={
                    "source": "file",
                    "path": str(path),
                    "file_sha256": loaded.file_sha256,
                    "variant": loaded.metadata["training"]["variant"],
                    "steps": loaded.metadata["training"]["steps"],
                    "architecture": loaded.metadata["architecture"],
                },
            )
        )
    return specs


def fpfh_spec(voxel_size: float) -> FeatureSpec:
    """The FPFH features (Open3D) at ``voxel_size`` (m), shared by the FPFH methods."""
    from byoc_cli.pipeline import features as F

    return FeatureSpec(
        key="fpfh",
        extractor=F.FpfhExtractor(voxel_size),
        identity={
            "extractor": "fpfh",
            "voxel_size": float(voxel_size),
            "normal_radius": F.FPFH_NORMAL_RADIUS,
            "feature_radius": F.FPFH_FEATURE_RADIUS,
            "normal_max_nn": F.FPFH_NORMAL_MAX_NN,
            "feature_max_nn": F.FPFH_FEATURE_MAX_NN,
        },
        info={"source": "open3d", "voxel_size": float(voxel_size)},
    )


def feature_specs(methods: Sequence[Method]) -> list[FeatureSpec]:
    """The distinct feature specs of ``methods``, in first-use order."""
    out: list[FeatureSpec] = []
    for method in methods:
        if method.features is not None and all(method.features is not s for s in out):
            out.append(method.features)
    return out
