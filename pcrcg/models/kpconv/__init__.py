"""KPConv in plain PyTorch: kernel dispositions, the rigid convolution, blocks and the CPU pipeline."""

from pcrcg.models.kpconv.aggregation import KernelAggregation, kpconv_sparse
from pcrcg.models.kpconv.conv import KPConv, get_implementation, implementation, kpconv, set_implementation
from pcrcg.models.kpconv.kernel_points import kernel_points
from pcrcg.models.kpconv.ops import grid_subsample, nearest_neighbor, neighbor_counts, radius_neighbors, radius_pairs
from pcrcg.models.kpconv.pyramid import (
    FragmentPyramid,
    PyramidCache,
    PyramidSpec,
    TensorPyramid,
    build_pyramid,
    calibrate_limits,
    stack_pair,
)

__all__ = [
    "KPConv", "kpconv", "kpconv_sparse", "KernelAggregation", "implementation", "set_implementation",
    "get_implementation", "kernel_points", "grid_subsample", "nearest_neighbor", "neighbor_counts",
    "radius_neighbors", "radius_pairs", "FragmentPyramid", "PyramidCache", "PyramidSpec", "TensorPyramid",
    "build_pyramid", "calibrate_limits", "stack_pair",
]
