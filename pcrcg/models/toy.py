"""A synthetic pair for tests and benchmarks: a box room with furniture, two overlapping crops.

No files, no views: the data the models stage needs to be tested alone.
"""

from __future__ import annotations

import numpy as np

from pcrcg.data.dataset import PairSample
from pcrcg.geometry import invert, make_transform, random_rotation, transform_points


def _sample_box_faces(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, density: float,
                      skip_top: bool = False, skip_bottom: bool = False) -> np.ndarray:
    """Points uniform on the faces of the axis-aligned box [lo, hi]; ``density`` points per m^2."""
    out = []
    size = hi - lo
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        area = size[u] * size[v]
        for side, val in ((0, lo[axis]), (1, hi[axis])):
            if axis == 2 and ((side == 1 and skip_top) or (side == 0 and skip_bottom)):
                continue
            n = max(1, int(rng.poisson(area * density)))
            p = np.empty((n, 3))
            p[:, axis] = val
            p[:, u] = lo[u] + rng.random(n) * size[u]
            p[:, v] = lo[v] + rng.random(n) * size[v]
            out.append(p)
    return np.concatenate(out, 0)


def box_room(rng: np.random.Generator, size=(3.0, 2.5, 2.0), n_boxes: int = 6, density: float = 400.0) -> np.ndarray:
    """A room (floor, ceiling, walls) with ``n_boxes`` random boxes on the floor: (N, 3) float32, metres."""
    size = np.asarray(size, float)
    parts = [_sample_box_faces(rng, np.zeros(3), size, density)]
    for _ in range(n_boxes):
        ext = rng.uniform([0.2, 0.2, 0.2], [0.8, 0.8, 1.2])
        base = rng.uniform([0.1, 0.1], size[:2] - ext[:2] - 0.1)
        lo = np.array([base[0], base[1], 0.0])
        parts.append(_sample_box_faces(rng, lo, lo + ext, density, skip_bottom=True))
    return np.concatenate(parts, 0).astype(np.float32)


def toy_pair(seed: int = 0, size=(3.0, 2.5, 2.0), density: float = 400.0, overlap_band: float = 0.6,
             noise: float = 0.003) -> PairSample:
    """Two crops of one box room along x that share a band of width ``overlap_band`` (m).

    The target is the room's left part in the room frame, the source the right part moved by a random
    rigid motion into its own frame; ``transform`` maps source into target.
    """
    rng = np.random.default_rng(seed)
    room = box_room(rng, size, density=density)
    mid = size[0] / 2
    tgt = room[room[:, 0] < mid + overlap_band / 2]
    src_w = room[room[:, 0] > mid - overlap_band / 2]
    G = make_transform(random_rotation(rng), rng.uniform(-1, 1, 3))
    src = transform_points(G, src_w.astype(np.float64)).astype(np.float32)
    src = src + rng.normal(0, noise, src.shape).astype(np.float32)
    tgt = tgt + rng.normal(0, noise, tgt.shape).astype(np.float32)
    overlap = float(np.mean(np.abs(src_w[:, 0] - mid) < overlap_band / 2))
    return PairSample(scene=f"toy{seed}", i=0, j=1, src_points=src, tgt_points=tgt.astype(np.float32),
                      src_colors=np.zeros_like(src), tgt_colors=np.zeros_like(tgt), transform=invert(G),
                      overlap=overlap)
