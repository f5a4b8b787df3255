"""Pairs of fragments: overlap, the 3DMatch information matrix, and benchmark assignment.

* overlap(i, j) = the larger of the two directions' fraction of points that have a point of the
  other fragment within ``radius`` (3.75 cm) once aligned by the ground truth;
* ``gt.info`` = sum over corresponding points p (in fragment i's frame) of G^T G,
  G = [I | -[p]x] (translation first), over at most 5000 correspondences as in the official files
  (their ``info[0,0]``, the count, is min(#correspondences, 5000));
* pairs with overlap >= 10% are kept: 3DMatch if > 30%, 3DLoMatch otherwise.

Overlaps and correspondences are computed on a copy of each fragment voxel-averaged to
``overlap_voxel`` (2.5 cm, the resolution Predator trains at), which makes them independent of the
fragment's storage density.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pcrcg.geometry import skew, transform_points

OVERLAP_RADIUS = 0.0375
MAX_INFO_POINTS = 5000


@dataclass
class PairConfig:
    overlap_radius: float = OVERLAP_RADIUS
    overlap_voxel: float = 0.025
    min_overlap: float = 0.10
    lo_match_max: float = 0.30


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Average the points falling into each voxel. (N, 3) -> (M, 3) float64, order by voxel key."""
    points = np.asarray(points, dtype=np.float64)
    if voxel <= 0 or len(points) == 0:
        return points
    keys = np.floor(points / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inv.ravel(), points)
    return sums / counts[:, None]


def overlap_ratio(
    pts_i: np.ndarray, pts_j: np.ndarray, T_ji: np.ndarray, radius: float = OVERLAP_RADIUS,
    tree_i: cKDTree | None = None, tree_j: cKDTree | None = None,
) -> float:
    """max(frac of j within radius of i, frac of i within radius of j) with j mapped by T_ji (j into i)."""
    pj = transform_points(T_ji, pts_j)
    tree_i = tree_i if tree_i is not None else cKDTree(pts_i)
    d_j, _ = tree_i.query(pj, k=1, distance_upper_bound=radius)
    tree_pj = cKDTree(pj)
    d_i, _ = tree_pj.query(pts_i, k=1, distance_upper_bound=radius)
    return float(max(np.mean(d_j < radius), np.mean(d_i < radius)))


def info_matrix(
    pts_i: np.ndarray, pts_j: np.ndarray, T_ji: np.ndarray, radius: float = OVERLAP_RADIUS,
    max_points: int = MAX_INFO_POINTS, seed: int = 0,
) -> np.ndarray:
    """The 6x6 information matrix of a pair (translation first), 3DMatch convention.

    Correspondences are the points of fragment i with a point of the aligned fragment j within
    ``radius``; at most ``max_points`` of them, drawn with ``seed``.
    """
    pj = transform_points(T_ji, pts_j)
    d, _ = cKDTree(pj).query(pts_i, k=1, distance_upper_bound=radius)
    p = pts_i[d < radius].astype(np.float64)
    if len(p) > max_points:
        p = p[np.random.default_rng(seed).choice(len(p), max_points, replace=False)]
    return info_from_points(p)


def info_from_points(p: np.ndarray) -> np.ndarray:
    """sum_p G^T G with G = [I | -[p]x] for points p (K, 3).

    The data code's information matrix (what ``gt.info`` is written with). It is deliberately not
    :func:`pcrcg.evaluation.metrics.information_matrix`, which computes the same matrix in closed form
    from the point sums: that one is the independent implementation :mod:`pcrcg.data.checks`
    re-derives ``gt.info`` with (issue 17), so the two must stay two; ``tests/test_data_synth.py``
    holds them equal.
    """
    S = skew(p)  # (K, 3, 3)
    G = np.concatenate([np.broadcast_to(np.eye(3), S.shape), -S], axis=2)  # (K, 3, 6)
    return np.einsum("kai,kaj->ij", G, G)


def benchmark_of(overlap: float, cfg: PairConfig) -> str | None:
    """'3DMatch' (> lo_match_max), '3DLoMatch' ([min_overlap, lo_match_max]) or None."""
    if overlap > cfg.lo_match_max:
        return "3DMatch"
    if overlap >= cfg.min_overlap:
        return "3DLoMatch"
    return None
