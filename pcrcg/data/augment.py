"""Augmentation of a fragment pair that keeps its RGB-D views consistent with the points.

:func:`augment_pair` ``(sample, rng, rotation_range_deg=360.0, noise_std=0.005, which="random")
-> PairSample``: rotates one fragment (``src`` or ``tgt``, chosen by ``rng`` unless ``which`` says)
about its frame origin by a random rotation of angle uniform in ``[0, rotation_range_deg]`` about a
uniformly random axis (Predator's augmentation), moves that fragment's camera poses with it
(``View.transformed(T)``), updates ``transform`` so that it still maps src into tgt, and adds
Gaussian noise of std ``noise_std`` metres to the points of both fragments (views are not noised).
The input sample is not modified. Lifting features after augmentation gives the same features as
before (up to the point noise): the cameras see the rotated points exactly where they saw the
original ones.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pcrcg.geometry import invert, make_transform, random_rotation, transform_points


def rotate_fragment(points: np.ndarray, views: list, T: np.ndarray) -> tuple[np.ndarray, list]:
    """Apply the rigid ``T`` (4x4) to a fragment: points (N, 3) float32 and the views' poses."""
    pts = transform_points(T, np.asarray(points, dtype=np.float64)).astype(np.float32)
    return pts, [v.transformed(T) for v in views]


def augment_pair(sample, rng: np.random.Generator, rotation_range_deg: float = 360.0,
                 noise_std: float = 0.005, which: str = "random"):
    """A randomly rotated and noised copy of ``sample`` (see the module docstring)."""
    if which not in ("random", "src", "tgt"):
        raise ValueError(f"which must be 'random', 'src' or 'tgt', got {which!r}")
    if noise_std < 0 or rotation_range_deg < 0:
        raise ValueError("rotation_range_deg and noise_std must be >= 0")
    R = random_rotation(rng, np.radians(rotation_range_deg))
    T_aug = make_transform(R, np.zeros(3))
    rot_src = bool(rng.random() < 0.5) if which == "random" else which == "src"
    src_pts, tgt_pts = sample.src_points, sample.tgt_points
    src_views, tgt_views = list(sample.src_views), list(sample.tgt_views)
    T = np.asarray(sample.transform, dtype=np.float64)
    if rot_src:
        src_pts, src_views = rotate_fragment(src_pts, src_views, T_aug)
        T = T @ invert(T_aug)  # new src = T_aug old src  =>  tgt = T T_aug^-1 new src
    else:
        tgt_pts, tgt_views = rotate_fragment(tgt_pts, tgt_views, T_aug)
        T = T_aug @ T
    if noise_std > 0:
        src_pts = (src_pts + rng.normal(0.0, noise_std, src_pts.shape)).astype(np.float32)
        tgt_pts = (tgt_pts + rng.normal(0.0, noise_std, tgt_pts.shape)).astype(np.float32)
    else:
        src_pts, tgt_pts = np.array(src_pts, np.float32), np.array(tgt_pts, np.float32)
    return replace(sample, src_points=src_pts, tgt_points=tgt_pts, transform=T,
                   src_views=src_views, tgt_views=tgt_views)
