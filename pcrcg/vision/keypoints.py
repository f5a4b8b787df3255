"""What the 2D matchers and the feature maps share: keypoints, matches, their verification and the
fixed descriptor projection.

The bottom of :mod:`pcrcg.vision`: it imports no other module of it, so that :mod:`pcrcg.vision.learned`
(DISK + LightGlue) and :mod:`pcrcg.vision.matching` (SIFT/ORB, the cache, the view pairs) on top of it,
and :mod:`pcrcg.vision.features` on top of those, import one way. Callers keep importing these names
from :mod:`pcrcg.vision.matching` (``Matches``, ``ImageFeatures``, ``verify_fundamental``) and
:mod:`pcrcg.vision.features` (``sift_projection``).

Public API
----------
* :class:`Matches` ``(uv_a (K, 2) float32, uv_b (K, 2) float32, confidence (K,) float32 in (0, 1])``:
  matched pixels of two input images (pixel centres at integers).
* :class:`ImageFeatures` keypoints + descriptors of one image, in the matched image's pixels.
* :func:`check_image`: an (H, W, 3) uint8 RGB image or a ValueError.
* :func:`verify_fundamental` ``(ma, mb, cfg) -> (inliers, epipolar distance) | None``: the
  fundamental-matrix RANSAC every matcher ends with.
* :func:`sift_projection` ``(dim, seed, kind) -> (dim, 128) float32``: the fixed seeded 128 -> dim
  reduction of dense SIFT's and DISK's descriptors.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pcrcg.errors import ConfigError

# cv2 is imported inside the functions that use it (here as in matching): importing pcrcg.vision,
# which pcrcg.config does, stays cheap.


@dataclass
class Matches:
    """Matched pixels of two images: ``uv_a[k]`` in image a matches ``uv_b[k]`` in image b."""

    uv_a: np.ndarray
    uv_b: np.ndarray
    confidence: np.ndarray

    def __post_init__(self) -> None:
        self.uv_a = np.asarray(self.uv_a, dtype=np.float32).reshape(-1, 2)
        self.uv_b = np.asarray(self.uv_b, dtype=np.float32).reshape(-1, 2)
        self.confidence = np.asarray(self.confidence, dtype=np.float32).reshape(-1)
        if not len(self.uv_a) == len(self.uv_b) == len(self.confidence):
            raise ValueError("Matches: uv_a, uv_b and confidence must have the same length")

    def __len__(self) -> int:
        return len(self.confidence)

    @classmethod
    def empty(cls) -> "Matches":
        return cls(np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), np.zeros(0, np.float32))

    def swapped(self) -> "Matches":
        """The same matches seen from image b."""
        return Matches(self.uv_b, self.uv_a, self.confidence)


@dataclass
class ImageFeatures:
    """Keypoints of one image, in the pixels of the image as matched (resized to ``size``).

    ``uv`` (K, 2) float32 (u, v); ``descriptors`` (K, D) (float32 for SIFT and DISK, uint8 for ORB) or
    None when nothing was found; ``scores`` (K,) float32 detector responses; ``size`` (h, w) of the
    matched image; ``scale`` (sx, sy) from input pixels to matched pixels.
    """

    uv: np.ndarray
    descriptors: np.ndarray | None
    scores: np.ndarray
    size: tuple[int, int]
    scale: tuple[float, float] = (1.0, 1.0)

    def __len__(self) -> int:
        return 0 if self.descriptors is None else int(len(self.uv))

    def to_input(self, uv: np.ndarray) -> np.ndarray:
        """(K, 2) matched-image pixels -> input-image pixels (pixel-centre convention)."""
        uv = np.asarray(uv, dtype=np.float64)
        sx, sy = self.scale
        return np.stack([(uv[:, 0] + 0.5) / sx - 0.5, (uv[:, 1] + 0.5) / sy - 0.5], 1)


def check_image(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB image, got shape {img.shape}")
    if img.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {img.dtype}")
    return img


def _epipolar_distance(F: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Symmetric epipolar distance (pixels) of matches pa <-> pb (K, 2) under F (b^T F a = 0)."""
    ha = np.concatenate([pa, np.ones((len(pa), 1))], 1).astype(np.float64)
    hb = np.concatenate([pb, np.ones((len(pb), 1))], 1).astype(np.float64)
    lb = ha @ F.T  # epipolar lines in b
    la = hb @ F  # epipolar lines in a
    num = np.abs(np.sum(hb * lb, axis=1))
    da = num / np.maximum(np.hypot(la[:, 0], la[:, 1]), 1e-12)
    db = num / np.maximum(np.hypot(lb[:, 0], lb[:, 1]), 1e-12)
    return 0.5 * (da + db)


def verify_fundamental(ma: np.ndarray, mb: np.ndarray, cfg: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """Fundamental-matrix RANSAC (``ransac_threshold`` px, seeded) on candidate matches ma <-> mb (K, 2).

    Returns ``(inliers (K,) bool, epipolar distance (K_in,) of the inliers)``, or None when it fails
    or keeps fewer than ``max(min_matches, 8)``. The geometric verification of every method.
    ``cfg``: a :class:`pcrcg.vision.matching.MatcherConfig` (``ransac_threshold``, ``min_matches``, ``seed``).
    """
    import cv2

    need = max(int(cfg.min_matches), 8)
    if len(ma) < need:
        return None
    ma, mb = np.asarray(ma, np.float64), np.asarray(mb, np.float64)
    cv2.setRNGSeed(int(cfg.seed))
    F, inl = cv2.findFundamentalMat(ma, mb, cv2.FM_RANSAC, float(cfg.ransac_threshold), 0.999, 2000)
    if F is None or inl is None or F.shape != (3, 3):
        return None
    inl = inl.reshape(-1).astype(bool)
    if inl.sum() < need:
        return None
    return inl, _epipolar_distance(F, ma[inl], mb[inl])


def sift_projection(dim: int, seed: int = 0, kind: str = "sift") -> np.ndarray:
    """A fixed (seeded) 128 -> dim projection with orthonormal rows: (dim, 128) float32 (dense SIFT's
    and DISK's reduction; ``kind`` names the features in the error)."""
    if not 1 <= dim <= 128:
        raise ConfigError("features.dim", dim, f"1..128 for features={kind}")
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(128, dim)))
    return q.T.astype(np.float32)
