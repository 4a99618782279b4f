"""File input and output: point clouds, depth images, intrinsics, transforms, 3DMatch ground
truth, atomic writes.

Depends on nothing of byoc-cli's but :mod:`byoc_cli.errors`; works on numpy arrays. open3d
is imported lazily, only to read PCD and XYZ/PTS files.
"""

from byoc_cli.io.atomic import atomic_write, atomic_write_bytes, atomic_write_text
from byoc_cli.io.depth import (
    Intrinsics,
    depth_to_points,
    read_depth_cloud,
    read_depth_image,
    read_intrinsics,
)
from byoc_cli.io.matrix import format_transform, read_transform, write_transform
from byoc_cli.io.pointcloud import (
    SUPPORTED_EXTENSIONS,
    LoadedCloud,
    check_units,
    read_point_cloud,
    write_ply,
)
from byoc_cli.io.threedmatch import (
    BenchmarkScene,
    GtInfoRecord,
    GtRecord,
    PreparedPair,
    discover_benchmark,
    discover_prepared_pairs,
    read_gt_info,
    read_gt_log,
    read_gt_overlap,
)
from byoc_cli.io.threedmatch_write import write_gt_info, write_gt_log, write_gt_overlap

__all__ = [
    "SUPPORTED_EXTENSIONS",
    "BenchmarkScene",
    "GtInfoRecord",
    "GtRecord",
    "Intrinsics",
    "LoadedCloud",
    "PreparedPair",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_units",
    "depth_to_points",
    "discover_benchmark",
    "discover_prepared_pairs",
    "format_transform",
    "read_depth_cloud",
    "read_depth_image",
    "read_gt_info",
    "read_gt_log",
    "read_gt_overlap",
    "read_intrinsics",
    "read_point_cloud",
    "read_transform",
    "write_gt_info",
    "write_gt_log",
    "write_gt_overlap",
    "write_ply",
    "write_transform",
]
