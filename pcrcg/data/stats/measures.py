"""The measures of ``python -m pcrcg.data.stats``: small pure functions, arrays in, numbers out.

Points are (N, 3) arrays in metres; no function writes to its input.

* :func:`voxel_downsample` / :func:`count_voxels`: Open3D's ``voxel_down_sample`` (the one the
  project's baselines and Predator use), so "points at 2.5 cm" means what it means there.
* :func:`extent_sides`: sides of the bounding box, PCA-aligned (default) or axis-aligned, between
  the 2nd and 98th percentiles of the coordinates by default (stray points do not count).
* :func:`planarity`: share of the points within ``distance`` of the ``n_planes`` largest planes
  found one after the other by Open3D's RANSAC ``segment_plane`` (each plane's inliers removed
  before the next), seeded with ``o3d.utility.random.seed``.
* :func:`estimate_normals` + :func:`orientation_entropy`: the entropy in bits of the normals'
  *axial* orientation (a normal and its negative are the same orientation: normals estimated by
  local PCA have no sign), over a Fibonacci binning: each normal goes to the nearest, up to sign,
  of ``n_cells`` axes spread by a Fibonacci spiral over the hemisphere (:func:`fibonacci_axes`).
  The cells have nearly equal areas (within about +-25% of the mean, the extremes at the equator
  seam; uniformly spread orientations score 7.642 of the 7.644 bits of 200 equal cells). Unlike a
  latitude-longitude grid folded onto a hemisphere, no cell boundary runs along a whole great
  circle, where in the camera frame the normals of floors and side walls would straddle it.
  200 cells: at most log2(200) = 7.64 bits; one plane gives 0 bits, the three face orientations
  of a cube log2(3) = 1.58 bits.
* :func:`overlap_histogram`, :func:`hole_rate`, :func:`median_depth`, :func:`covisibility`,
  :func:`summarize`.
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np

#: bin edges of the overlap histograms (fractions)
OVERLAP_EDGES = tuple(round(0.1 * k, 1) for k in range(11))


def _as_points(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"expected points of shape (N, 3), got {p.shape}")
    return p


def _cloud(points: np.ndarray):
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_as_points(points)))


# --------------------------------------------------------------------------- sizes


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """points (N, 3) -> (M, 3) float64: the centroid of the points in each occupied voxel
    (Open3D ``voxel_down_sample``); ``voxel <= 0`` returns a float64 copy."""
    p = _as_points(points)
    if voxel <= 0 or len(p) == 0:
        return p.copy()
    return np.asarray(_cloud(p).voxel_down_sample(float(voxel)).points)


def count_voxels(points: np.ndarray, voxel: float = 0.025) -> int:
    """Number of points (N, 3) left after voxel downsampling at ``voxel`` metres (occupied voxels)."""
    return int(len(voxel_downsample(points, voxel)))


def extent_sides(points: np.ndarray, pca: bool = True, trim: float = 2.0) -> np.ndarray:
    """Sides (3,) in metres of the bounding box of points (N, 3).

    ``pca=True``: the box aligned with the principal axes of the points, sides sorted from the
    longest; ``pca=False``: the axis-aligned box in the points' own frame, sides in x, y, z order.
    ``trim`` (percent): each side spans the ``trim``-th to the ``100 - trim``-th percentile of the
    coordinates along it, so that a few stray points do not set the size (0: the full box).
    """
    p = _as_points(points)
    if len(p) == 0:
        return np.full(3, np.nan)
    if pca:
        c = p - p.mean(0)
        _, vecs = np.linalg.eigh(c.T @ c)
        p = c @ vecs
    if trim > 0:
        lo, hi = np.percentile(p, [trim, 100.0 - trim], axis=0)
    else:
        lo, hi = p.min(0), p.max(0)
    sides = hi - lo
    return np.sort(sides)[::-1] if pca else sides


# --------------------------------------------------------------------------- planes


def planarity(
    points: np.ndarray,
    n_planes: int = 4,
    distance: float = 0.02,
    voxel: float = 0.05,
    seed: int = 0,
    ransac_n: int = 3,
    iterations: int = 1000,
) -> float:
    """Share (0..1) of the points within ``distance`` of the ``n_planes`` largest RANSAC planes.

    points (N, 3) are first downsampled at ``voxel`` metres (0: as given). Planes are found one
    after the other with Open3D's ``segment_plane(distance, ransac_n, iterations)``, removing each
    plane's inliers before the next; the random generator is seeded with ``seed`` first, so the
    result is reproducible. NaN for no points.
    """
    import open3d as o3d

    p = voxel_downsample(points, voxel)
    n = len(p)
    if n == 0:
        return float("nan")
    o3d.utility.random.seed(int(seed))
    cur = _cloud(p)
    found = 0
    for _ in range(int(n_planes)):
        if len(cur.points) < max(int(ransac_n), 3):
            break
        _, inliers = cur.segment_plane(float(distance), int(ransac_n), int(iterations))
        if len(inliers) == 0:
            break
        found += len(inliers)
        cur = cur.select_by_index(inliers, invert=True)
    return found / n


# --------------------------------------------------------------------------- normals


def estimate_normals(points: np.ndarray, radius: float = 0.10, max_nn: int = 30) -> np.ndarray:
    """Unit normals (N, 3) of points (N, 3) by local PCA over neighbours within ``radius`` (at most
    ``max_nn``; Open3D ``estimate_normals``). Their sign is arbitrary."""
    import open3d as o3d

    pcd = _cloud(points)
    if len(pcd.points) == 0:
        return np.zeros((0, 3))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius), max_nn=int(max_nn)))
    return np.asarray(pcd.normals).copy()


def fibonacci_axes(n_cells: int = 200) -> np.ndarray:
    """Unit vectors (n_cells, 3) spread evenly over the hemisphere z > 0 by a Fibonacci spiral:
    z = 1 - (k + 0.5) / n_cells (equal steps in z are equal areas), azimuth k times the golden angle.
    With their negatives they cover the sphere nearly uniformly."""
    k = np.arange(int(n_cells), dtype=np.float64)
    z = 1.0 - (k + 0.5) / n_cells
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def axial_cells(normals: np.ndarray, n_cells: int = 200) -> np.ndarray:
    """Cell index (N,) in ``[0, n_cells)`` of the axial orientation of vectors (N, 3): the nearest
    of the :func:`fibonacci_axes` up to sign (largest ``|n . a|``), so ``n`` and ``-n`` share a
    cell and cells have nearly equal areas. Vectors need not be unit length (not zero)."""
    v = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(v) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.argmax(np.abs(v @ fibonacci_axes(n_cells).T), axis=1)


def entropy_bits(counts: Sequence[float]) -> float:
    """Shannon entropy in bits of a histogram (counts >= 0); NaN for an empty one."""
    c = np.asarray(counts, dtype=np.float64).ravel()
    s = c.sum()
    if s <= 0:
        return float("nan")
    p = c[c > 0] / s
    return float(max(0.0, -(p * np.log2(p)).sum()))


def orientation_entropy(normals: np.ndarray, n_cells: int = 200) -> float:
    """Entropy in bits of the axial orientations of normals (N, 3) over :func:`axial_cells`
    (at most log2(n_cells): 7.64 bits for 200). Zero or non-finite normals are ignored; NaN when
    none is left."""
    v = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    norm = np.linalg.norm(v, axis=1)
    v = v[np.isfinite(norm) & (norm > 1e-9)]
    if len(v) == 0:
        return float("nan")
    return entropy_bits(np.bincount(axial_cells(v, n_cells), minlength=n_cells))


def normal_entropy(points: np.ndarray, voxel: float = 0.05, radius: float = 0.10, max_nn: int = 30,
                   n_cells: int = 200) -> float:
    """Normal-orientation entropy (bits) of points (N, 3): downsampled at ``voxel`` (0: as given),
    normals over ``radius`` metres (at most ``max_nn`` neighbours), then :func:`orientation_entropy`.
    NaN for fewer than 3 points."""
    p = voxel_downsample(points, voxel)
    if len(p) < 3:
        return float("nan")
    return orientation_entropy(estimate_normals(p, radius, max_nn), n_cells)


# --------------------------------------------------------------------------- pairs and frames


def overlap_histogram(overlaps: Iterable[float], edges: Sequence[float] = OVERLAP_EDGES) -> list[int]:
    """Counts (len(edges) - 1,) of overlaps (fractions) in ``[edges[k], edges[k+1])``, the last bin
    closed; NaN values are left out."""
    o = np.asarray(list(overlaps), dtype=np.float64)
    o = o[np.isfinite(o)]
    counts, _ = np.histogram(np.clip(o, edges[0], edges[-1]), bins=np.asarray(edges, dtype=np.float64))
    return [int(c) for c in counts]


def hole_rate(depth: np.ndarray) -> float:
    """Share (0..1) of pixels of a depth image (H, W) without depth (0 or not finite)."""
    d = np.asarray(depth)
    if d.size == 0:
        return float("nan")
    bad = (d == 0) | ~np.isfinite(d) if np.issubdtype(d.dtype, np.floating) else (d == 0)
    return float(np.mean(bad))


def median_depth(depth: np.ndarray) -> float:
    """Median depth (metres) over the pixels of a depth image (H, W) that have depth (> 0 and
    finite); NaN when none has."""
    d = np.asarray(depth, dtype=np.float64)
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if d.size else float("nan")


COVIS_EDGES = (0.0, 0.3, 0.5, 1.0)  # co-visibility bins of the view pairs' matches


def covisibility(depth_a: np.ndarray, pose_a: np.ndarray, depth_b: np.ndarray, pose_b: np.ndarray,
                 K: np.ndarray, step: int = 2, tol: float = 0.1) -> float:
    """Share (0..1) of frame a's pixels with depth (every ``step``-th row and column) whose point
    lands inside frame b, in front of it, at the depth b measures there within ``tol`` of that
    depth: how much of a's view b sees too. Depths (H, W) in metres (0 = none), camera-to-world
    poses (4, 4), the depth camera's intrinsics K (3, 3); both frames of one size. NaN when a has
    no depth."""
    za = np.asarray(depth_a, dtype=np.float64)[::step, ::step]
    db = np.asarray(depth_b, dtype=np.float64)
    H, W = db.shape
    v, u = np.mgrid[0 : depth_a.shape[0] : step, 0 : depth_a.shape[1] : step]
    m = np.isfinite(za) & (za > 0)
    if not m.any():
        return float("nan")
    z = za[m]
    pts = np.stack([(u[m] - K[0, 2]) * z / K[0, 0], (v[m] - K[1, 2]) * z / K[1, 1], z], 1)  # (n, 3) in a
    rel = np.linalg.inv(pose_b) @ pose_a
    q = pts @ rel[:3, :3].T + rel[:3, 3]  # (n, 3) in b
    front = q[:, 2] > 1e-3
    zq = np.where(front, q[:, 2], 1.0)
    ub = np.rint(K[0, 0] * q[:, 0] / zq + K[0, 2])
    vb = np.rint(K[1, 1] * q[:, 1] / zq + K[1, 2])
    inside = front & (ub >= 0) & (ub < W) & (vb >= 0) & (vb < H)
    seen = db[vb[inside].astype(np.int64), ub[inside].astype(np.int64)]
    agree = np.isfinite(seen) & (seen > 0) & (np.abs(seen - q[inside, 2]) <= tol * q[inside, 2])
    return float(agree.sum() / m.sum())


def summarize(values: Iterable[float]) -> dict[str, float | int | None]:
    """``n``, ``mean``, ``median``, ``p10``, ``p90``, ``min``, ``max`` of the finite values
    (None when there are none)."""
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0, "mean": None, "median": None, "p10": None, "p90": None, "min": None, "max": None}
    q10, q50, q90 = np.percentile(v, [10, 50, 90])
    return {"n": int(v.size), "mean": float(v.mean()), "median": float(q50), "p10": float(q10),
            "p90": float(q90), "min": float(v.min()), "max": float(v.max())}


def max_orientation_entropy(n_cells: int = 200) -> float:
    """log2 of the number of cells: the entropy of perfectly spread orientations."""
    return math.log2(n_cells)
