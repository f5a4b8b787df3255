"""Small synthetic registration problems for tests and benchmarks (no files needed).

* :func:`box_room` a textured room (floor, walls, boxes) as points and colors;
* :func:`make_fragment_pair` two overlapping crops of it, each in its own frame;
* :func:`correspondence_problem` putative correspondences of a moved copy of it, a share of them true
  (RANSAC's input);
* :func:`simulate_outputs` descriptor / overlap / matchability arrays that behave like a trained
  network's (descriptors are random Fourier features of the true position plus noise);
* :func:`write_layout` a tiny data set in the 3DMatch layout (fragments + benchmark files).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcrcg.geometry import invert, make_transform, random_rotation, transform_points


def box_room(rng: np.random.Generator, n_points: int = 30000, size=(4.0, 3.0, 2.5), n_boxes: int = 6
             ) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) and colors (N, 3) in [0, 1] of a room with boxes; colors vary with position."""
    L, W, H = size

    def plane(o, u, v, n):
        s = rng.random((n, 2))
        return np.asarray(o, float) + s[:, :1] * np.asarray(u, float) + s[:, 1:] * np.asarray(v, float)

    area = np.array([L * W, L * H, W * H, W * H, L * H])
    counts = np.maximum((0.7 * n_points * area / area.sum()).astype(int), 10)
    parts = [plane([0, 0, 0], [L, 0, 0], [0, W, 0], counts[0]), plane([0, 0, 0], [L, 0, 0], [0, 0, H], counts[1]),
             plane([0, 0, 0], [0, W, 0], [0, 0, H], counts[2]), plane([L, 0, 0], [0, W, 0], [0, 0, H], counts[3])]
    per_box = max(int(0.3 * n_points / max(n_boxes, 1) / 3), 10)
    for _ in range(n_boxes):
        c = rng.uniform([0.3, 0.3, 0.0], [L - 1.0, W - 1.0, 0.0])
        e = rng.uniform(0.3, 0.9, 3)
        parts += [plane(c + [0, 0, e[2]], [e[0], 0, 0], [0, e[1], 0], per_box),
                  plane(c, [e[0], 0, 0], [0, 0, e[2]], per_box), plane(c, [0, e[1], 0], [0, 0, e[2]], per_box),
                  plane(c + [e[0], 0, 0], [0, e[1], 0], [0, 0, e[2]], per_box)]
    pts = np.concatenate(parts)
    f = rng.normal(size=(3, 3)) * 4.0
    colors = 0.5 + 0.5 * np.sin(pts @ f + rng.uniform(0, 6, 3))
    return pts, np.clip(colors, 0, 1)


def voxel_downsample(points: np.ndarray, voxel: float, colors: np.ndarray | None = None):
    """Keep the first point per voxel: (M, 3) points (and (M, 3) colors)."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    return (points[first], colors[first]) if colors is not None else points[first]


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
    lo, hi = points[:, axis].min(), points[:, axis].max()
    ext = hi - lo
    s_mask = points[:, axis] < lo + ext * (1 - crop)
    t_mask = points[:, axis] > lo + ext * crop
    sw, sc = voxel_downsample(points[s_mask], voxel, colors[s_mask])
    tw, tc = voxel_downsample(points[t_mask], voxel, colors[t_mask])
    A_s = make_transform(random_rotation(rng, max_angle), rng.normal(scale=0.5, size=3)) @ make_transform(np.eye(3), -sw.mean(0))
    A_t = make_transform(random_rotation(rng, max_angle), rng.normal(scale=0.5, size=3)) @ make_transform(np.eye(3), -tw.mean(0))
    from scipy.spatial import cKDTree

    d, _ = cKDTree(tw).query(sw)
    return FragmentPair(
        transform_points(A_s, sw).astype(np.float32), transform_points(A_t, tw).astype(np.float32),
        sc.astype(np.float32), tc.astype(np.float32), A_t @ invert(A_s), sw, tw, d < 1.5 * voxel, A_s, A_t,
    )


def correspondence_problem(seed: int, n: int, inlier_ratio: float
                           ) -> tuple[np.random.Generator, np.ndarray, np.ndarray, np.ndarray]:
    """n room-surface points and a rigidly moved, 1 cm-noisy copy, with putative correspondences of which
    about ``inlier_ratio`` are true -> (the generator after drawing, src (n, 3), tgt (n, 3), corr (n, 2))."""
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


def write_layout(root: str | Path, seed: int = 0, scene: str = "room", n_fragments: int = 5,
                 voxel: float = 0.03, n_points: int = 20000) -> Path:
    """A tiny data set in the 3DMatch layout: ``n_fragments`` overlapping crops of one room,
    each in its own frame, and 3DMatch / 3DLoMatch benchmark files (all pairs i < j split by
    overlap at 30 %; info matrices from the true overlap). Returns the root."""
    from scipy.spatial import cKDTree

    from pcrcg.data.layout import Layout, PairRecord, write_gt_info, write_gt_log, write_gt_overlap, write_ply, write_split
    from pcrcg.evaluation.metrics import information_matrix

    rng = np.random.default_rng(seed)
    pts, cols = box_room(rng, n_points)
    layout = Layout(root)
    layout.fragments_dir(scene).mkdir(parents=True, exist_ok=True)
    lo, hi = pts[:, 0].min(), pts[:, 0].max()
    width = 0.5 * (hi - lo)  # 5 fragments: neighbours overlap ~75 %, i/i+2 ~50 %, i/i+3 ~25 %
    frags = []
    for f in range(n_fragments):
        a = lo + (hi - lo - width) * f / max(n_fragments - 1, 1)
        m = (pts[:, 0] >= a) & (pts[:, 0] <= a + width)
        w, c = voxel_downsample(pts[m], voxel, cols[m])
        A = make_transform(random_rotation(rng, np.pi / 3), rng.normal(scale=0.3, size=3)) @ make_transform(np.eye(3), -w.mean(0))
        write_ply(layout.fragment(scene, f), transform_points(A, w), c)
        frags.append((w, A))
    recs = {"3DMatch": [], "3DLoMatch": []}
    infos = {"3DMatch": [], "3DLoMatch": []}
    for i in range(n_fragments):
        for j in range(i + 1, n_fragments):
            wi, Ai = frags[i]
            wj, Aj = frags[j]
            d, _ = cKDTree(wi).query(wj)
            ov_j = d < 1.5 * voxel
            ov = float(min(ov_j.mean(), (cKDTree(wj).query(wi)[0] < 1.5 * voxel).mean()))
            if ov < 0.05:
                continue
            b = "3DMatch" if ov > 0.3 else "3DLoMatch"
            recs[b].append(PairRecord(scene, i, j, Ai @ invert(Aj), ov, n_fragments))
            infos[b].append(information_matrix(transform_points(Aj, wj[ov_j])))
    for b in recs:
        d = layout.benchmark_dir(b, scene)
        d.mkdir(parents=True, exist_ok=True)
        write_gt_log(d / "gt.log", recs[b])
        write_gt_info(d / "gt.info", recs[b], infos[b])
        write_gt_overlap(d / "gt_overlap.log", recs[b])
    write_split(layout.split_file("test"), [scene])
    return Path(root)
