"""Sparse 3-D convolution in plain PyTorch (no compiled extension), CPU and CUDA.

A sparse tensor is a set of active sites with one feature row each:

* ``coords (N, 4)`` int64, rows ``[batch, x, y, z]``. At tensor stride ``s`` the spatial
  part is in units of that level's cells: ``x = floor(x_0 / s)`` for a stride-1 site
  ``x_0``. Several clouds share one tensor through the batch column.
* ``feats (N, C)`` float; ``feats[i]`` belongs to ``coords[i]``.

Every sparse tensor derived from one input shares a :class:`CoordinateManager`, which
owns the site sets of every stride and caches each kernel map, so a map is built once per
batch and per stride and reused by all the layers at that stride (submanifold maps per
kernel size, the k2/s2 down-sampling maps and their transposes).

A kernel map lists, for each kernel offset ``k``, pairs ``(in_idx, out_idx)``: output site
``out_idx[p]`` receives ``feats[in_idx[p]] @ weight[k]``. Weights are shaped
``(K, C_in, C_out)``. Offsets of a kernel of odd size ``k`` are ordered like
``torch.cartesian_prod(r, r, r)`` with ``r = arange(-(k // 2), k // 2 + 1)``, i.e. like the
spatial dimensions of ``torch.nn.functional.conv3d``'s weight (cross-correlation: the output
at ``p`` reads the input at ``p + offset``). The eight k2/s2 offsets are the octants
``(dx, dy, dz)`` in ``{0, 1}^3`` ordered ``dx * 4 + dy * 2 + dz``: the coarse site ``q``
reads the fine site ``2 q + (dx, dy, dz)``, as ``conv3d(kernel_size=2, stride=2)`` does, and
the transposed convolution writes back to exactly those fine sites.

The convolution gathers the input rows of one offset into a contiguous block, multiplies
it by that offset's ``(C_in, C_out)`` weight and adds the product into the output rows
(``index_add_``); the centre offset of a submanifold convolution is one dense matmul.
Every multiply-add is a useful one (no zero padding for missing neighbours). Results are
bit-identical from run to run on CPU. Neighbours are found by packing sites into int64 keys
and looking the shifted keys up in a dense table over the bounding box (binary search in
the sorted keys when the box is very large); only half of the offsets are searched, the
other half mirrors them.

On a 2-core CPU a 64 -> 64 3x3x3 convolution on a 19k-voxel surface runs at about 0.55-0.65
of the FLOP rate of a dense matmul of the same size (``benchmarks/sparse_conv.py``). Each
convolution issues about three small ops per offset: on a machine whose cores are busy
with other processes, OpenMP's default busy waiting can turn every parallel region into a
scheduler time slice; ``OMP_WAIT_POLICY=PASSIVE`` or ``torch.set_num_threads(1)`` avoids it.

Modules: ``maps.py`` (site sets, kernel maps, :class:`CoordinateManager`), ``ops.py``
(:func:`sparse_conv` and its autograd), ``tensor.py`` (:class:`SparseTensor`), ``layers.py``
(convolution modules), ``pointwise.py`` (batch norm, ReLU).
"""

from byoc_cli.models.sparse.layers import StridedConv, SubmanifoldConv, TransposedConv
from byoc_cli.models.sparse.maps import (
    MAX_KERNEL_SIZE,
    NUM_OCTANTS,
    TABLE_MAX_CELLS,
    CoordinateManager,
    KernelMap,
    kernel_offsets,
)
from byoc_cli.models.sparse.ops import sparse_conv
from byoc_cli.models.sparse.pointwise import SparseBatchNorm, SparseReLU
from byoc_cli.models.sparse.tensor import SparseTensor, sparse_cat

__all__ = [
    "MAX_KERNEL_SIZE",
    "NUM_OCTANTS",
    "TABLE_MAX_CELLS",
    "CoordinateManager",
    "KernelMap",
    "SparseBatchNorm",
    "SparseReLU",
    "SparseTensor",
    "StridedConv",
    "SubmanifoldConv",
    "TransposedConv",
    "kernel_offsets",
    "sparse_cat",
    "sparse_conv",
]
