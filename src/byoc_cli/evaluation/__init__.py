"""Evaluation layer of byoc-cli: 3DMatch feature-match recall and registration recall
(``byoc eval-fmr``), pairwise accuracy on posed RGB-D video (``byoc eval-pairs``), with every
method on the same pairs.

The names below are imported from their modules (and torch with them) when first used.
"""

from byoc_cli.lazy import lazy_exports

#: exported name -> its module
_EXPORTS = {
    "FeatureCache": "byoc_cli.evaluation.cache",
    "file_identity": "byoc_cli.evaluation.cache",
    "FmrConfig": "byoc_cli.evaluation.fmr",
    "FmrResult": "byoc_cli.evaluation.fmr",
    "evaluate_fmr": "byoc_cli.evaluation.fmr",
    "load_benchmark_pairs": "byoc_cli.evaluation.fmr",
    "pair_seed": "byoc_cli.evaluation.fmr",
    "METHOD_NAMES": "byoc_cli.evaluation.method_names",
    "Method": "byoc_cli.evaluation.methods",
    "build_methods": "byoc_cli.evaluation.methods",
    "parse_method_names": "byoc_cli.evaluation.method_names",
    "chamfer_distance": "byoc_cli.evaluation.metrics",
    "correspondence_inlier_ratio": "byoc_cli.evaluation.metrics",
    "fused_chamfer": "byoc_cli.evaluation.metrics",
    "nn_inlier_ratio": "byoc_cli.evaluation.metrics",
    "recall_by_group": "byoc_cli.evaluation.metrics",
    "registration_rmse": "byoc_cli.evaluation.metrics",
    "PairsConfig": "byoc_cli.evaluation.pairs",
    "PairsResult": "byoc_cli.evaluation.pairs",
    "evaluate_pairs": "byoc_cli.evaluation.pairs",
    "prepared_pairs": "byoc_cli.evaluation.pairs",
    "rgbd_pairs": "byoc_cli.evaluation.pairs",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports("byoc_cli.evaluation", _EXPORTS)
