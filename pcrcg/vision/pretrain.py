"""Pure stages of the 2D pretraining (Pri3D's view-invariant contrastive learning).

Pri3D (Hou et al., ICCV 2021) learns per-pixel features from RGB-D sequences: two views of the same
scene, pixel correspondences from depth and camera poses, and a point-level InfoNCE loss that pulls
the features of corresponding pixels together and pushes the other sampled pixels apart. Its
defaults, which this project follows: temperature 0.4, 1024 sampled correspondences per pair, view
pairs that overlap by at least 30%.

Public API (NumPy in / out for geometry, torch for features)
-----------------------------------------------------------
* :func:`relative_pose` ``(pose_src, pose_tgt) -> (4, 4)``: maps source-camera points into the target
  camera (poses camera-to-world).
* :func:`pixel_correspondences` ``(depth_src, K_src, depth_tgt, K_tgt, T_tgt_src, ...) ->``
  :class:`PixelMatches`: every source pixel with depth, back-projected, moved into the target camera
  and projected; kept when it lands inside the target image, in front of the camera, and the target
  depth at the nearest pixel agrees with the reprojected depth within
  ``depth_tolerance + depth_tolerance_rel * z`` (the visibility check: occluded or unobserved points
  are rejected).
* :func:`overlap_ratio` ``(...) -> float``: fraction of the source's valid pixels visible in the target.
* :func:`select_view_pairs` ``(depths, poses, K, ...) -> list[(a, b, overlap)]``: the frame pairs of one
  sequence whose frame distance is in ``[min_gap, max_gap]`` and whose two-way overlap
  ``min(ov(a->b), ov(b->a))`` is in ``[min_overlap, max_overlap]``.
* :func:`sample_matches` ``(matches, n, rng) -> PixelMatches``: ``n`` of them at random (all if fewer).
* :func:`crop_pair` ``(matches, src_shape, tgt_shape, crop, rng) -> (corner_src, corner_tgt, matches)``:
  random crops of both views around a shared correspondence (training on crops: more steps per second).
* :func:`gather_pixels` ``(feat (C, H, W), pix (N, 2) (v, u)) -> (N, C)``.
* :func:`info_nce` ``(f_src (N, C), f_tgt (N, C), temperature=0.4, symmetric=True) -> scalar``:
  cross-entropy of the cosine-similarity logits ``f_src_i . f_tgt_j / T`` with the diagonal as the
  target (the other sampled points of the pair are the negatives).
* :func:`match_accuracy` ``(feat_src, feat_tgt, src_pix, tgt_uv, tgt_valid, threshold) -> (acc, hits)``:
  nearest-neighbour (cosine) matching of source pixels against *every* valid target pixel; a hit when
  the matched pixel lies within ``threshold`` pixels of the true correspondence.
* :func:`color_jitter` ``(images (B, 3, H, W) in [0, 1], strength, generator) -> images``: per-image
  brightness and contrast change (the two views of a pair get independent ones).
* :func:`resize_view` ``(color, depth, K, size) -> (color, depth, K)``: area-resized color,
  nearest-neighbour depth (no depth mixing across edges), intrinsics scaled to match;
  :func:`resize_depth` ``(depth, K, size) -> (depth, K)`` the depth part alone.

Conventions: pixel ``(v, u)`` integer indices (row, column) as returned by
:func:`pcrcg.geometry.backproject`; ``uv`` float ``(u, v)`` as returned by :func:`pcrcg.geometry.project`;
pixel centres at integers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from pcrcg.device import argmax_rows
from pcrcg.geometry import backproject, invert, project, scale_intrinsics, transform_points

# Pri3D's published settings
PRI3D_TEMPERATURE = 0.4
PRI3D_POINTS = 1024
PRI3D_MIN_OVERLAP = 0.3


# --------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class PixelMatches:
    """Visible correspondences from a source view into a target view.

    ``src_pix`` (M, 2) int64 (v, u) source pixels; ``tgt_uv`` (M, 2) float64 (u, v) exact projection
    in the target; ``tgt_pix`` (M, 2) int64 (v, u) nearest target pixel; ``n_valid`` source pixels had
    depth (before the stride), ``n_in_view`` of them projected inside the target image.
    """

    src_pix: np.ndarray
    tgt_uv: np.ndarray
    tgt_pix: np.ndarray
    n_valid: int
    n_in_view: int

    def __len__(self) -> int:
        return int(self.src_pix.shape[0])

    @property
    def overlap(self) -> float:
        """Visible / valid source pixels (0 when the source has no depth)."""
        return len(self) / self.n_valid if self.n_valid else 0.0

    def subset(self, idx: np.ndarray) -> "PixelMatches":
        return PixelMatches(self.src_pix[idx], self.tgt_uv[idx], self.tgt_pix[idx], self.n_valid, self.n_in_view)


def relative_pose(pose_src: np.ndarray, pose_tgt: np.ndarray) -> np.ndarray:
    """(4, 4) mapping source-camera points into the target camera; poses are camera-to-world."""
    return invert(np.asarray(pose_tgt, dtype=np.float64)) @ np.asarray(pose_src, dtype=np.float64)


def pixel_correspondences(depth_src: np.ndarray, K_src: np.ndarray, depth_tgt: np.ndarray, K_tgt: np.ndarray,
                          T_tgt_src: np.ndarray, depth_tolerance: float = 0.05, depth_tolerance_rel: float = 0.02,
                          stride: int = 1) -> PixelMatches:
    """Visible pixel correspondences source -> target (see the module docstring).

    depth_src (H, W), depth_tgt (H', W') float metres (0 = none); K_* (3, 3); T_tgt_src (4, 4).
    ``stride`` subsamples the source pixel grid (pair selection uses a coarse grid).
    """
    pts, vu = backproject(np.asarray(depth_src), np.asarray(K_src, dtype=np.float64), stride)
    n_valid = int(pts.shape[0])
    h, w = depth_tgt.shape
    empty = PixelMatches(np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros((0, 2), np.int64), n_valid, 0)
    if n_valid == 0:
        return empty
    pts_t = transform_points(np.asarray(T_tgt_src, dtype=np.float64), pts)
    uv, z = project(pts_t, np.asarray(K_tgt, dtype=np.float64))
    front = z > 1e-6
    ui = np.rint(uv[:, 0])
    vi = np.rint(uv[:, 1])
    inside = front & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    n_in_view = int(inside.sum())
    idx = np.nonzero(inside)[0]
    ui_i = ui[idx].astype(np.int64)
    vi_i = vi[idx].astype(np.int64)
    d_t = depth_tgt[vi_i, ui_i].astype(np.float64)
    zz = z[idx]
    visible = (d_t > 0) & (np.abs(d_t - zz) <= depth_tolerance + depth_tolerance_rel * zz)
    keep = idx[visible]
    return PixelMatches(vu[keep].astype(np.int64), uv[keep], np.stack([vi_i[visible], ui_i[visible]], 1),
                        n_valid, n_in_view)


def overlap_ratio(depth_src: np.ndarray, K_src: np.ndarray, depth_tgt: np.ndarray, K_tgt: np.ndarray,
                  T_tgt_src: np.ndarray, depth_tolerance: float = 0.05, depth_tolerance_rel: float = 0.02,
                  stride: int = 8) -> float:
    """Fraction of the source's valid pixels (on a ``stride`` grid) visible in the target."""
    return pixel_correspondences(depth_src, K_src, depth_tgt, K_tgt, T_tgt_src, depth_tolerance,
                                 depth_tolerance_rel, stride).overlap


def select_view_pairs(depths: Sequence[np.ndarray], poses: np.ndarray, K: np.ndarray, min_gap: int = 1,
                      max_gap: int = 30, min_overlap: float = PRI3D_MIN_OVERLAP, max_overlap: float = 0.9,
                      stride: int = 8, depth_tolerance: float = 0.05,
                      depth_tolerance_rel: float = 0.02) -> list[tuple[int, int, float]]:
    """Pairs ``(a, b, overlap)`` (indices into ``depths``, a < b) of one sequence of frames.

    depths: F arrays (H, W); poses (F, 4, 4) camera-to-world; K (3, 3) for every frame. A pair is kept
    when ``min_gap <= b - a <= max_gap`` and ``min_overlap <= min(ov(a->b), ov(b->a)) <= max_overlap``.
    """
    n = len(depths)
    out = []
    for a in range(n):
        for b in range(a + max(1, min_gap), min(n, a + max_gap + 1)):
            T_ba = relative_pose(poses[a], poses[b])
            ov_ab = overlap_ratio(depths[a], K, depths[b], K, T_ba, depth_tolerance, depth_tolerance_rel, stride)
            if ov_ab < min_overlap:
                continue
            ov_ba = overlap_ratio(depths[b], K, depths[a], K, invert(T_ba), depth_tolerance, depth_tolerance_rel,
                                  stride)
            ov = min(ov_ab, ov_ba)
            if min_overlap <= ov <= max_overlap:
                out.append((a, b, float(ov)))
    return out


def sample_matches(matches: PixelMatches, n: int, rng: np.random.Generator) -> PixelMatches:
    """``n`` correspondences drawn without replacement (all of them, shuffled, when fewer)."""
    m = len(matches)
    idx = rng.permutation(m)[: min(n, m)]
    return matches.subset(idx)


def crop_pair(matches: PixelMatches, src_shape: Sequence[int], tgt_shape: Sequence[int], crop: Sequence[int],
              rng: np.random.Generator) -> tuple[tuple[int, int], tuple[int, int], PixelMatches] | None:
    """Random crops ``crop`` = (h, w) of a source and a target image that share correspondences.

    A correspondence is drawn at random; each crop is placed uniformly among the positions that hold
    its end in that image. Returns the crops' top-left corners ``(v0, u0)`` (source, target) and the
    correspondences inside both crops in crop coordinates (``tgt_uv`` shifted too); None without
    correspondences. ``src_shape``/``tgt_shape``: (H, W) of the full images (>= crop).
    """
    if len(matches) == 0:
        return None
    h, w = int(crop[0]), int(crop[1])
    k = int(rng.integers(len(matches)))

    def corner(pix: np.ndarray, shape: Sequence[int]) -> tuple[int, int]:
        out = []
        for c, size, n in zip(pix, (h, w), shape):
            lo, hi = max(0, int(c) - size + 1), min(int(c), int(n) - size)
            out.append(int(rng.integers(lo, hi + 1)))
        return out[0], out[1]

    cs, ct = corner(matches.src_pix[k], src_shape), corner(matches.tgt_pix[k], tgt_shape)
    sp = matches.src_pix - np.array(cs)
    tp = matches.tgt_pix - np.array(ct)
    keep = ((sp[:, 0] >= 0) & (sp[:, 0] < h) & (sp[:, 1] >= 0) & (sp[:, 1] < w)
            & (tp[:, 0] >= 0) & (tp[:, 0] < h) & (tp[:, 1] >= 0) & (tp[:, 1] < w))
    uv = matches.tgt_uv[keep] - np.array([ct[1], ct[0]], dtype=np.float64)
    return cs, ct, PixelMatches(sp[keep], uv, tp[keep], matches.n_valid, matches.n_in_view)


def resize_view(color: np.ndarray, depth: np.ndarray, K: np.ndarray,
                size: Sequence[int] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Resize a view to ``size`` = (H, W): color (H, W, 3) uint8 by area, depth (H, W) float32 by nearest
    neighbour (no depths mixed across edges), K (3, 3) scaled (pixel-centre convention)."""
    import cv2

    if size is None or tuple(color.shape[:2]) == tuple(size):
        return color, depth, np.asarray(K, dtype=np.float64)
    d, K2 = resize_depth(depth, K, size)
    c = cv2.resize(color, (int(size[1]), int(size[0])), interpolation=cv2.INTER_AREA)
    return c, d, K2


def resize_depth(depth: np.ndarray, K: np.ndarray, size: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) resized to ``size`` = (h, w) by nearest neighbour at the new pixel centres (cv2's
    INTER_NEAREST is off by half a pixel) and the intrinsics (3, 3) scaled to match."""
    h, w = int(size[0]), int(size[1])
    sy, sx = h / depth.shape[0], w / depth.shape[1]
    ys = np.clip(np.floor((np.arange(h) + 0.5) / sy).astype(np.int64), 0, depth.shape[0] - 1)
    xs = np.clip(np.floor((np.arange(w) + 0.5) / sx).astype(np.int64), 0, depth.shape[1] - 1)
    d = np.ascontiguousarray(depth[ys][:, xs])
    return d, scale_intrinsics(np.asarray(K, dtype=np.float64), sx, sy)


# --------------------------------------------------------------------------- features and loss


def gather_pixels(feat: torch.Tensor, pix: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Features of pixels: feat (C, H, W), pix (N, 2) integer (v, u) -> (N, C) (differentiable)."""
    pix = torch.as_tensor(pix, dtype=torch.long, device=feat.device)
    return feat[:, pix[:, 0], pix[:, 1]].t()


def info_nce(f_src: torch.Tensor, f_tgt: torch.Tensor, temperature: float = PRI3D_TEMPERATURE,
             symmetric: bool = True) -> torch.Tensor:
    """Point-level InfoNCE: f_src, f_tgt (N, C), row i of both is a corresponding pair -> scalar.

    Features are L2-normalised; logits ``(f_src @ f_tgt.T) / temperature``; the loss is the
    cross-entropy with target i for row i (``symmetric``: averaged with the target->source direction).
    With perfect one-hot features it is ``log(1 + (N - 1) exp(-1 / T))``; with constant ones ``log N``.
    """
    if f_src.shape != f_tgt.shape or f_src.dim() != 2:
        raise ValueError(f"info_nce expects two (N, C) tensors of one shape, got {tuple(f_src.shape)} "
                         f"and {tuple(f_tgt.shape)}")
    a = F.normalize(f_src, dim=1)
    b = F.normalize(f_tgt, dim=1)
    logits = a @ b.t() / float(temperature)
    target = torch.arange(a.shape[0], device=a.device)
    loss = F.cross_entropy(logits, target)
    if symmetric:
        loss = 0.5 * (loss + F.cross_entropy(logits.t(), target))
    return loss


@torch.no_grad()
def match_accuracy(feat_src: torch.Tensor, feat_tgt: torch.Tensor, src_pix: np.ndarray | torch.Tensor,
                   tgt_uv: np.ndarray | torch.Tensor, tgt_valid: np.ndarray | torch.Tensor, threshold: float = 3.0,
                   chunk: int = 512) -> tuple[float, np.ndarray]:
    """Nearest-neighbour pixel matching accuracy of one view pair.

    feat_src (C, H, W), feat_tgt (C, H', W'); src_pix (N, 2) (v, u) query pixels; tgt_uv (N, 2) (u, v)
    their true positions in the target; tgt_valid (H', W') bool: the candidate target pixels (those
    with depth). Each query takes the candidate of highest cosine similarity; a hit when that pixel is
    within ``threshold`` pixels (Euclidean) of the true position. Returns (fraction of hits, hits (N,) bool).
    """
    dev = feat_src.device
    valid = torch.as_tensor(np.asarray(tgt_valid) if not torch.is_tensor(tgt_valid) else tgt_valid, device=dev)
    cand = torch.nonzero(valid.bool(), as_tuple=False)  # (P, 2) (v, u)
    n = int(src_pix.shape[0])
    if n == 0 or cand.shape[0] == 0:
        return float("nan") if n == 0 else 0.0, np.zeros(n, dtype=bool)
    q = F.normalize(gather_pixels(feat_src, src_pix).float(), dim=1)  # (N, C)
    c = F.normalize(feat_tgt[:, cand[:, 0], cand[:, 1]].t().float(), dim=1)  # (P, C)
    true_uv = torch.as_tensor(np.asarray(tgt_uv) if not torch.is_tensor(tgt_uv) else tgt_uv, dtype=torch.float64,
                              device=dev)
    hits = []
    for s in range(0, n, chunk):
        nn_idx = argmax_rows(q[s:s + chunk] @ c.t())
        pred = cand[nn_idx].to(torch.float64).flip(1)  # (u, v)
        err = torch.linalg.norm(pred - true_uv[s:s + chunk], dim=1)
        hits.append(err <= threshold)
    h = torch.cat(hits).cpu().numpy()
    return float(h.mean()), h


def color_jitter(images: torch.Tensor, strength: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Per-image brightness and contrast factors uniform in [1 - strength, 1 + strength].

    images (B, 3, H, W) in [0, 1] -> same shape, clamped to [0, 1]. ``strength`` 0 returns the input.
    """
    if strength <= 0:
        return images
    b = images.shape[0]
    r = torch.rand((b, 2), generator=generator).to(images.device, images.dtype)
    bright = 1.0 + strength * (2 * r[:, 0] - 1)
    contrast = 1.0 + strength * (2 * r[:, 1] - 1)
    mean = images.mean(dim=(1, 2, 3), keepdim=True)
    out = (images - mean) * contrast.view(b, 1, 1, 1) + mean
    return (out * bright.view(b, 1, 1, 1)).clamp_(0.0, 1.0)
