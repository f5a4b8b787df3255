"""Pairs and registration problems cut from the fixtures' box room (tests and benchmarks; tiny data,
never used by a run).

* :func:`toy_pair` a :class:`~pcrcg.data.dataset.PairSample` of two overlapping crops (the models);
* :func:`make_fragment_pair` two overlapping crops, each voxelised and moved into its own frame;
* :func:`correspondence_problem` putative correspondences of a moved copy of room points, a share of
  them true (RANSAC's input);
* :func:`simulate_outputs` descriptor / overlap / matchability arrays that behave like a trained
  network's (descriptors are random Fourier features of the true position plus noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcrcg.data.dataset import PairSample
from pcrcg.geometry import invert, make_transform, random_rotation, transform_points
from pcrcg.testing.rooms import box_room


def toy_pair(seed: int = 0, size=(3.0, 2.5, 2.0), density: float = 400.0, overlap_band: float = 0.6,
             noise: float = 0.003) -> PairSample:
    """Two crops of one box room (``density`` points per m^2) along x that share a band of width
    ``overlap_band`` (m); no colors.

    The target is the room's left part in the room frame, the source the right part moved by a random
    rigid motion into its own frame; ``transform`` maps source into target.
    """
    rng = np.random.default_rng(seed)
    room, _ = box_room(rng, size=size, density=density)
    mid = size[0] / 2
    tgt = room[room[:, 0] < mid + overlap_band / 2].astype(np.float32)
    src_w = room[room[:, 0] > mid - overlap_band / 2]
    G = make_transform(random_rotation(rng), rng.uniform(-1, 1, 3))
    src = transform_points(G, src_w).astype(np.float32)
    src = src + rng.normal(0, noise, src.shape).astype(np.float32)
    tgt = tgt + rng.normal(0, noise, tgt.shape).astype(np.float32)
    overlap = float(np.mean(np.abs(src_w[:, 0] - mid) < overlap_band / 2))
    return PairSample(scene=f"toy{seed}", i=0, j=1, src_points=src, tgt_points=tgt,
                      src_colors=np.zeros_like(src), tgt_colors=np.zeros_like(tgt), transform=invert(G),
                      overlap=overlap)


@dataclass
class FragmentPair:
    """src/tgt points (and colors) in their own frames; ``transform`` (4, 4) maps src into tgt;
    ``src_world`` / ``tgt_world`` the same points in the room frame; ``src_overlap`` (N,) bool."""

    src_points: np.ndarray
    tgt_points: np.ndarray
    src_colors: np.ndarray
    tgt_colors: np.ndarray
    transform: np.ndarray
    src_world: np.ndarray
    tgt_world: np.ndarray
    src_overlap: np.ndarray
    src_pose: np.ndarray  # (4, 4) world -> src frame
    tgt_pose: np.ndarray  # (4, 4) world -> tgt frame


def voxel_crop(points: np.ndarray, colors: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """A crop of the room as a fragment: points (float64) and colors averaged per ``voxel`` cell by the
    real fragment step (:func:`pcrcg.data.fusion.voxel_average`)."""
    from pcrcg.data.fusion import voxel_average  # Open3D loads only where fragments are made

    p, c = voxel_average(points, colors, voxel)
    return p.astype(np.float64), c


def make_fragment_pair(
    rng: np.random.Generator,
    points: np.ndarray,
    colors: np.ndarray,
    crop: float = 0.3,
    voxel: float = 0.025,
    max_angle: float = np.pi,
    axis: int = 0,
) -> FragmentPair:
    """Two crops along ``axis`` overlapping by about ``1 - 2 crop`` of the extent, each moved
    into a random frame (rotation up to ``max_angle``)."""
    from scipy.spatial import cKDTree

    lo, hi = points[:, axis].min(), points[:, axis].max()
    ext = hi - lo
    s_mask = points[:, axis] < lo + ext * (1 - crop)
    t_mask = points[:, axis] > lo + ext * crop
    sw, sc = voxel_crop(points[s_mask], colors[s_mask], voxel)
    tw, tc = voxel_crop(points[t_mask], colors[t_mask], voxel)
    A_s = make_transform(random_rotation(rng, max_angle), rng.normal(scale=0.5, size=3)) @ make_transform(np.eye(3), -sw.mean(0))
    A_t = make_transform(random_rotation(rng, max_angle), rng.normal(scale=0.5, size=3)) @ make_transform(np.eye(3), -tw.mean(0))
    d, _ = cKDTree(tw).query(sw)
    return FragmentPair(
        transform_points(A_s, sw).astype(np.float32), transform_points(A_t, tw).astype(np.float32),
        sc.astype(np.float32), tc.astype(np.float32), A_t @ invert(A_s), sw, tw, d < 1.5 * voxel, A_s, A_t,
    )


def correspondence_problem(seed: int, n: int, inlier_ratio: float
                           ) -> tuple[np.random.Generator, np.ndarray, np.ndarray, np.ndarray]:
    """n room-surface points and a rigidly moved, 1 cm-noisy copy, with putative correspondences of which
    about ``inlier_ratio`` are true -> (the generator after drawing, src (n, 3), tgt (n, 3), corr (n, 2)).

    Its draws are those RANSAC's recorded test results were made with: keep them."""
    rng = np.random.default_rng(seed)
    pts, _ = box_room(rng, 4 * n)
    src = pts[rng.choice(len(pts), n, replace=False)]
    T = make_transform(random_rotation(rng), rng.normal(size=3))
    tgt = transform_points(T, src) + rng.normal(scale=0.01, size=src.shape)
    perm = np.arange(n)
    bad = rng.random(n) >= inlier_ratio
    perm[bad] = rng.integers(0, n, int(bad.sum()))
    return rng, src, tgt, np.stack([np.arange(n), perm], 1)


def simulate_outputs(
    rng: np.random.Generator, world: np.ndarray, overlap: np.ndarray, noise: float, dim: int = 32,
    scale: float = 0.06, fourier: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Descriptors (N, dim) unit-norm, overlap (N,), matchability (N,) float32 for points whose
    true room positions are ``world`` (N, 3); ``overlap`` (N,) bool is the true overlap.

    Pass the same ``fourier = (W (dim, 3), b (dim,))`` for both fragments of a pair.
    """
    if fourier is None:
        fourier = (rng.normal(scale=1.0 / scale, size=(dim, 3)), rng.uniform(0, 2 * np.pi, dim))
    Wf, bf = fourier
    d = np.cos(world @ Wf.T + bf) + rng.normal(scale=noise, size=(len(world), len(bf)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ov = np.clip(0.15 + 0.75 * overlap * rng.uniform(0.6, 1.0, len(world)) + rng.normal(0, 0.08, len(world)), 0.01, 1)
    m = rng.uniform(0.2, 1.0, len(world))
    return d.astype(np.float32), ov.astype(np.float32), m.astype(np.float32)
