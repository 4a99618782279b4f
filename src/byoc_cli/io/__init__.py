"""File input and output: point clouds, depth images, intrinsics, transforms, 3DMatch ground
truth, atomic writes.

Depends on nothing of byoc-cli's but :mod:`byoc_cli.errors` and :mod:`byoc_cli.lazy`; works on
numpy arrays. open3d is imported lazily, only to read PCD and XYZ/PTS files.

The names below are imported from their modules (and numpy with them) when first used, so
that the commands that only write files (and ``byoc COMMAND --help``) stay light.
"""

from byoc_cli.lazy import lazy_exports

#: exported name -> its module
_EXPORTS = {
    "atomic_write": "byoc_cli.io.atomic",
    "atomic_write_bytes": "byoc_cli.io.atomic",
    "atomic_write_text": "byoc_cli.io.atomic",
    "Intrinsics": "byoc_cli.io.depth",
    "depth_to_points": "byoc_cli.io.depth",
    "read_depth_cloud": "byoc_cli.io.depth",
    "read_depth_image": "byoc_cli.io.depth",
    "read_intrinsics": "byoc_cli.io.depth",
    "format_transform": "byoc_cli.io.matrix",
    "read_transform": "byoc_cli.io.matrix",
    "write_transform": "byoc_cli.io.matrix",
    "SUPPORTED_EXTENSIONS": "byoc_cli.io.pointcloud",
    "LoadedCloud": "byoc_cli.io.pointcloud",
    "check_units": "byoc_cli.io.pointcloud",
    "read_point_cloud": "byoc_cli.io.pointcloud",
    "write_ply": "byoc_cli.io.pointcloud",
    "BenchmarkScene": "byoc_cli.io.threedmatch",
    "GtInfoRecord": "byoc_cli.io.threedmatch",
    "GtRecord": "byoc_cli.io.threedmatch",
    "PreparedPair": "byoc_cli.io.threedmatch",
    "discover_benchmark": "byoc_cli.io.threedmatch",
    "discover_prepared_pairs": "byoc_cli.io.threedmatch",
    "read_gt_info": "byoc_cli.io.threedmatch",
    "read_gt_log": "byoc_cli.io.threedmatch",
    "read_gt_overlap": "byoc_cli.io.threedmatch",
    "write_gt_info": "byoc_cli.io.threedmatch_write",
    "write_gt_log": "byoc_cli.io.threedmatch_write",
    "write_gt_overlap": "byoc_cli.io.threedmatch_write",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports("byoc_cli.io", _EXPORTS)
