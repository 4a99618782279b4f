"""Matching layer of byoc-cli: chunked feature nearest neighbours, ratio-test correspondences."""

from byoc_cli.matching.ratio import (
    KNN,
    Correspondences,
    feature_knn,
    mutual_filter,
    ratio_test_correspondences,
)

__all__ = [
    "KNN",
    "Correspondences",
    "feature_knn",
    "mutual_filter",
    "ratio_test_correspondences",
]
