"""Evaluation layer of byoc-cli: 3DMatch feature-match recall and registration recall
(``byoc eval-fmr``), pairwise accuracy on posed RGB-D video (``byoc eval-pairs``), with every
method on the same pairs.
"""

from byoc_cli.evaluation.cache import FeatureCache, file_identity
from byoc_cli.evaluation.fmr import (
    FmrConfig,
    FmrResult,
    evaluate_fmr,
    load_benchmark_pairs,
    pair_seed,
)
from byoc_cli.evaluation.methods import METHOD_NAMES, Method, build_methods, parse_method_names
from byoc_cli.evaluation.metrics import (
    chamfer_distance,
    correspondence_inlier_ratio,
    fused_chamfer,
    nn_inlier_ratio,
    recall_by_group,
    registration_rmse,
)
from byoc_cli.evaluation.pairs import (
    PairsConfig,
    PairsResult,
    evaluate_pairs,
    prepared_pairs,
    rgbd_pairs,
)

__all__ = [
    "METHOD_NAMES",
    "FeatureCache",
    "FmrConfig",
    "FmrResult",
    "Method",
    "PairsConfig",
    "PairsResult",
    "build_methods",
    "chamfer_distance",
    "correspondence_inlier_ratio",
    "evaluate_fmr",
    "evaluate_pairs",
    "file_identity",
    "fused_chamfer",
    "load_benchmark_pairs",
    "nn_inlier_ratio",
    "pair_seed",
    "parse_method_names",
    "prepared_pairs",
    "recall_by_group",
    "registration_rmse",
    "rgbd_pairs",
]
