"""Statistics of data sets side by side: ``python -m pcrcg.data.stats ROOT [ROOT ...]``.

One column per data set (generated profiles, the fused red kitchen, a real scene root, or a bare
folder of fragments with ``--fragments-dir``), one row per measure; printed as Markdown and
written to ``<out>.md``, ``<out>.json`` and a picture ``<out>.png`` (see :mod:`.cli`).

The measures are small pure functions in :mod:`pcrcg.data.stats.measures`.
"""

from pcrcg.data.stats.measures import (
    OVERLAP_EDGES,
    axial_cells,
    count_voxels,
    entropy_bits,
    estimate_normals,
    extent_sides,
    fibonacci_axes,
    hole_rate,
    max_orientation_entropy,
    normal_entropy,
    orientation_entropy,
    overlap_histogram,
    planarity,
    summarize,
    voxel_downsample,
)

__all__ = [
    "OVERLAP_EDGES", "axial_cells", "count_voxels", "entropy_bits", "estimate_normals", "extent_sides", "fibonacci_axes", "hole_rate",
    "max_orientation_entropy", "normal_entropy", "orientation_entropy", "overlap_histogram", "planarity",
    "summarize", "voxel_downsample",
]
