"""File input and output: point clouds, depth images, intrinsics, transforms, atomic writes.

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

__all__ = [
    "SUPPORTED_EXTENSIONS",
    "Intrinsics",
    "LoadedCloud",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_units",
    "depth_to_points",
    "format_transform",
    "read_depth_cloud",
    "read_depth_image",
    "read_intrinsics",
    "read_point_cloud",
    "read_transform",
    "write_ply",
    "write_transform",
]
