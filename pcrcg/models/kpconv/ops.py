"""Point-cloud operations of the data pipeline (NumPy/SciPy, run on the CPU in the collate step).

Neighbour index arrays use KPConv's *shadow* convention: a row lists the indices of a query's
support points sorted by distance, padded with ``len(supports)`` (the shadow index), which the
network maps to a zero feature / a point at infinity.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def grid_subsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Barycentres of the points in each occupied cell of a ``voxel`` grid.

    points (N, 3) float -> (M, 3) float32, M <= N, in order of first cell index (deterministic).
    """
    if voxel <= 0:
        raise ValueError(f"voxel must be positive, got {voxel}")
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros((0, 3), np.float32)
    cell = np.floor(pts / voxel).astype(np.int64)
    cell -= cell.min(axis=0)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    # per axis, the cell sums in point order (np.add.at's order and float64 sums: the same barycentres bit for
    # bit, in ~80% of its time)
    sums = np.stack([np.bincount(inverse, weights=pts[:, c], minlength=len(counts)) for c in range(3)], axis=1)
    return (sums / counts[:, None]).astype(np.float32)


def support_tree(supports: np.ndarray) -> cKDTree:
    """The k-d tree of supports (N, 3) that :func:`radius_neighbors` and :func:`nearest_neighbor` search
    (build it once for several searches of the same supports)."""
    return cKDTree(np.asarray(supports, dtype=np.float64))


def radius_neighbors(
    queries: np.ndarray, supports: np.ndarray, radius: float, max_neighbors: int, workers: int = 1,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """Indices of the supports within ``radius`` of each query, nearest first.

    queries (M, 3), supports (N, 3) -> (M, H) int64 with H = min(max_neighbors, the largest count),
    padded with N (shadow). A query has at most ``max_neighbors`` neighbours (the farthest are dropped).
    ``tree``: :func:`support_tree` of these supports, when the caller has it.
    """
    n = len(supports)
    k = int(max(1, min(max_neighbors, n)))
    if len(queries) == 0 or n == 0:
        return np.full((len(queries), 1), n, dtype=np.int64)
    tree = tree if tree is not None else support_tree(supports)
    _, idx = tree.query(np.asarray(queries, dtype=np.float64), k=k, distance_upper_bound=radius, workers=workers)
    idx = np.asarray(idx, dtype=np.int64).reshape(len(queries), k)
    width = int(max(1, (idx < n).sum(axis=1).max()))
    return np.ascontiguousarray(idx[:, :width])


def nearest_neighbor(queries: np.ndarray, supports: np.ndarray, workers: int = 1,
                     tree: cKDTree | None = None) -> np.ndarray:
    """Index of the nearest support of each query: (M, 1) int64 (N when there are no supports).
    ``tree``: :func:`support_tree` of these supports, when the caller has it."""
    n = len(supports)
    if n == 0 or len(queries) == 0:
        return np.full((len(queries), 1), n, dtype=np.int64)
    tree = tree if tree is not None else support_tree(supports)
    _, idx = tree.query(np.asarray(queries, dtype=np.float64), k=1, workers=workers)
    return np.asarray(idx, dtype=np.int64).reshape(-1, 1)


def neighbor_counts(queries: np.ndarray, supports: np.ndarray, radius: float, workers: int = 1) -> np.ndarray:
    """Number of supports within ``radius`` of each query: (M,) int64 (for calibrating limits)."""
    if len(supports) == 0:
        return np.zeros(len(queries), np.int64)
    counts = support_tree(supports).query_ball_point(np.asarray(queries, dtype=np.float64), radius,
                                                     return_length=True, workers=workers)
    return np.asarray(counts, dtype=np.int64)


def radius_pairs(src: np.ndarray, tgt: np.ndarray, radius: float) -> np.ndarray:
    """All pairs (a, b) with |src[a] - tgt[b]| < radius: (C, 2) int64, sorted by (a, b)."""
    if len(src) == 0 or len(tgt) == 0:
        return np.zeros((0, 2), np.int64)
    ts, tt = support_tree(src), support_tree(tgt)
    coo = ts.sparse_distance_matrix(tt, radius, output_type="ndarray")
    pairs = np.stack([coo["i"], coo["j"]], axis=1).astype(np.int64)
    if len(pairs):
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    return pairs
