"""Fitting layer of byoc-cli: weighted Procrustes, randomized Procrustes, correspondence RANSAC,
second-order spatial compatibility.

Every estimator returns ``T_tgt_src`` (``x_tgt = R x_src + t``); the robust ones return a
:class:`FitResult`.
"""

from byoc_cli.fitting.compatibility import spatial_compatibility
from byoc_cli.fitting.procrustes import FitResult, weighted_procrustes, weighted_residuals
from byoc_cli.fitting.randomized import randomized_procrustes
from byoc_cli.fitting.ransac import ransac, required_iterations

__all__ = [
    "FitResult",
    "randomized_procrustes",
    "ransac",
    "required_iterations",
    "spatial_compatibility",
    "weighted_procrustes",
    "weighted_residuals",
]
