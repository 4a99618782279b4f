"""The ranges of the numbers a user gives, and the bound on the processes a run may start.

One place for both the CLI's option types (``cli/options.py``) and the core's checks of the
same settings from a config file (``training/config.py``, the weights metadata), so that a
value the command line refuses is refused from a file too. Nothing here imports torch.

The ranges are wide enough for any real use and narrow enough that every value survives the
float32 arithmetic of open3d and the encoders: ``1e-300`` m becomes 0 in float32, and a
learning rate of ``1e10`` turns the weights into NaN in one step.
"""

from __future__ import annotations

import os

#: Voxel sizes in metres (features, ICP, merged models, FPFH); the weights spec's maximum.
MIN_VOXEL_SIZE = 1e-4
MAX_VOXEL_SIZE = 10.0
#: TSDF voxel in metres, and the largest truncation distance in voxels: the blocks a depth
#: frame touches grow as truncation / voxel**3 (1 mm voxels, 4 mm truncation: 1.9 GB for five
#: VGA frames), so both are bounded.
MIN_TSDF_VOXEL = 2e-3
MAX_TSDF_VOXEL = 1.0
MAX_TRUNC_VOXELS = 16.0
#: Other lengths in metres (distances, depths, truncations, thresholds).
MIN_LENGTH = 1e-4
MAX_LENGTH = 1e4
#: ``--scale``: input units to metres (1e-6 for micrometres, 1e3 for kilometres).
MIN_SCALE = 1e-6
MAX_SCALE = 1e6
#: Depth-image units per metre (1 for float metres, 1000 for millimetres, 5000 for TUM).
MIN_DEPTH_SCALE = 1e-3
MAX_DEPTH_SCALE = 1e7
#: Angles in degrees.
MAX_DEGREES = 180.0
#: Adam's learning rate: (0, MAX_LR]; larger rates diverge on the first steps.
MAX_LR = 1.0
#: Any other positive number.
MIN_POSITIVE = 1e-12
MAX_POSITIVE = 1e12

#: The robust estimators' defaults (the registration recipe's; read without torch by the
#: commands' help): candidates of randomized Procrustes and correspondences per candidate
#: (the paper's section 3.1); RANSAC's limits, at most this many minimal sets, fewer once the
#: best inlier share makes this confidence of having drawn an all-inlier set.
NUM_SUBSETS = 100
SUBSET_SIZE = 20
MAX_ITERATIONS = 100_000
CONFIDENCE = 0.999
#: The largest values of the registration recipe's counts (a file or an option): points per
#: cloud in matching and matches per direction (a cloud file holds at most 30 million points),
#: RANSAC's minimal sets (100 times the default), randomized Procrustes' candidates and their
#: size (their product, at most 10 million correspondences, is one batched solve).
MAX_MATCH_POINTS = 30_000_000
MAX_RANSAC_ITERATIONS = 10_000_000
MAX_NUM_SUBSETS = 10_000
MAX_SUBSET_SIZE = 1_000
#: The most retries of a pair below the gate (``gate.retries``; each one costs about a
#: matching, a fit and a refinement).
MAX_RETRIES = 16
#: The largest inlier threshold, as a multiple of the voxel.
MAX_INLIER_FACTOR = 100.0

#: Data-loading worker processes per core this process may run on.
WORKERS_PER_CORE = 2


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # no affinity on this platform
        return max(1, os.cpu_count() or 1)


def max_workers() -> int:
    """The most worker processes a run starts: :data:`WORKERS_PER_CORE` per usable core."""
    return WORKERS_PER_CORE * usable_cores()
