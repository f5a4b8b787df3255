"""2D correspondences between RGB views: SIFT/ORB, ratio test, mutual check, F-RANSAC, cache.

Public API (other stages code against it)
-----------------------------------------
* :class:`MatcherConfig` ``(method="sift"|"orb", ratio=0.8, mutual=True, ransac_threshold=3.0,
  max_keypoints=4000, min_matches=8, pairs="paper"|"all", image_size=None, seed=0,
  contrast_threshold=0.04)``. ``min_matches`` applies to the candidates before RANSAC and to its
  inliers; a fundamental matrix fits any 8 matches, so a verification only means something well
  above 8 (the ``matcher2d`` configs use 12).
  ``ransac_threshold`` is in pixels of the image actually matched (``image_size`` when set).
* :class:`Matches` ``(uv_a (K, 2) float32, uv_b (K, 2) float32, confidence (K,) float32 in (0, 1])``;
  ``uv = (u, v) = (x, y)`` pixel coordinates of the *input* images (pixel centres at integers),
  whatever ``image_size`` the matcher resized them to internally.
* :func:`match_images` ``(img_a (H, W, 3) uint8 RGB, img_b, cfg) -> Matches``.
* :class:`MatchCache` ``(cache_dir)``: the paper's "match dumps" on disk, one ``.npz`` per image pair
  and matcher setting, reused across runs; :meth:`MatchCache.match` computes or loads.
* :func:`view_pairs` ``(n_src, n_tgt, mode) -> [(a, b), ...]`` which view pairs are matched:
  ``paper`` = (first, first), (last, last), (middle, middle); ``all`` = every cross pair.
* :func:`match_views` ``(src_views, tgt_views, cfg, cache=None) -> {(a, b): Matches}`` where
  ``uv_a`` lies in ``src_views[a]`` and ``uv_b`` in ``tgt_views[b]``.

Confidence of a match: ``(1 - d1/d2) * exp(-0.5 * (e / ransac_threshold)^2)`` with ``d1/d2`` the
Lowe distance ratio and ``e`` the symmetric epipolar distance (pixels) under the RANSAC fundamental
matrix; it lies in ``(1 - ratio) * 0.6 .. 1`` for kept matches, so every kept match weighs > 0.
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

METHODS = ("sift", "orb")
PAIR_MODES = ("paper", "all")
CACHE_VERSION = 1


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

    def key(self) -> dict[str, Any]:
        """The settings that change the matches (for cache keys)."""
        d = asdict(self)
        d.pop("pairs")  # which pairs are matched does not change one pair's matches
        d["image_size"] = list(self.image_size) if self.image_size else None
        return d


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

    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB image, got shape {img.shape}")
    if img.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {img.dtype}")
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


def match_images(img_a: np.ndarray, img_b: np.ndarray, cfg: MatcherConfig | None = None) -> Matches:
    """Match two RGB images (H, W, 3) uint8; returns matches in input-pixel coordinates.

    Steps: keypoints + descriptors (SIFT or ORB, at most ``max_keypoints``), nearest neighbours a->b
    with Lowe's ratio test (``d1 < ratio * d2``), mutual nearest-neighbour check b->a (``mutual``),
    fundamental-matrix RANSAC (``ransac_threshold`` px, seeded) keeping inliers. Fewer than
    ``max(min_matches, 8)`` surviving matches at any step gives empty :class:`Matches`.
    """
    import cv2

    cfg = cfg or MatcherConfig()
    ga, sxa, sya = _gray(img_a, cfg.image_size)
    gb, sxb, syb = _gray(img_b, cfg.image_size)
    pa, da = _detect(ga, cfg)
    pb, db = _detect(gb, cfg)
    need = max(int(cfg.min_matches), 8)
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
    cv2.setRNGSeed(int(cfg.seed))
    F, inl = cv2.findFundamentalMat(ma, mb, cv2.FM_RANSAC, float(cfg.ransac_threshold), 0.999, 2000)
    if F is None or inl is None or F.shape != (3, 3):
        return Matches.empty()
    inl = inl.reshape(-1).astype(bool)
    if inl.sum() < need:
        return Matches.empty()
    ma, mb, r = ma[inl], mb[inl], r[inl]
    e = _epipolar_distance(F, ma, mb)
    conf = (1.0 - r) * np.exp(-0.5 * (e / float(cfg.ransac_threshold)) ** 2)
    conf = np.clip(conf, 1e-3, 1.0)
    # back to input-pixel coordinates (pixel-centre convention)
    ua = np.stack([(ma[:, 0] + 0.5) / sxa - 0.5, (ma[:, 1] + 0.5) / sya - 0.5], 1)
    ub = np.stack([(mb[:, 0] + 0.5) / sxb - 0.5, (mb[:, 1] + 0.5) / syb - 0.5], 1)
    order = np.argsort(-conf, kind="stable")
    return Matches(ua[order], ub[order], conf[order])


# --------------------------------------------------------------------------- pairs of views


def view_pairs(n_src: int, n_tgt: int, mode: str = "paper") -> list[tuple[int, int]]:
    """Indices (a, b) of the src/tgt views to match.

    Views are ordered first, last, middle. ``paper``: (0, 0), (1, 1), (2, 2) up to the shorter list;
    ``all``: every (a, b).
    """
    if mode == "paper":
        return [(k, k) for k in range(min(n_src, n_tgt))]
    if mode == "all":
        return [(a, b) for a in range(n_src) for b in range(n_tgt)]
    raise ConfigError("matcher2d.pairs", mode, " | ".join(PAIR_MODES))


def match_views(
    src_views: Sequence[Any],
    tgt_views: Sequence[Any],
    cfg: MatcherConfig | None = None,
    cache: "MatchCache | None" = None,
) -> dict[tuple[int, int], Matches]:
    """Matches of the selected view pairs (``cfg.pairs``) of two fragments.

    ``src_views`` / ``tgt_views`` are :class:`pcrcg.data.dataset.View` lists. Returns
    ``{(a, b): Matches}`` with ``uv_a`` in ``src_views[a].color`` and ``uv_b`` in ``tgt_views[b].color``.
    """
    cfg = cfg or MatcherConfig()
    out = {}
    for a, b in view_pairs(len(src_views), len(tgt_views), cfg.pairs):
        va, vb = src_views[a], tgt_views[b]
        if cache is not None:
            out[(a, b)] = cache.match(va.color, vb.color, cfg, getattr(va, "color_path", None),
                                      getattr(vb, "color_path", None))
        else:
            out[(a, b)] = match_images(va.color, vb.color, cfg)
    return out


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


class MatchCache:
    """Matches on disk (the paper's match dumps): ``<cache_dir>/<hh>/<sha1>.npz``.

    The key hashes both images (file path + mtime + size, or the pixel bytes when no file) and the
    matcher settings (:meth:`MatcherConfig.key`). A cached file holds ``uv_a``, ``uv_b``,
    ``confidence`` and ``meta`` (JSON: the key material). Writes are atomic, so parallel jobs may
    share one cache. ``hits`` / ``misses`` count lookups of this instance.
    """

    def __init__(self, cache_dir: str | os.PathLike):
        self.dir = Path(cache_dir)
        self.hits = 0
        self.misses = 0

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

    def save(self, key: str, m: Matches, meta: str = "") -> Path:
        p = self.path(key)
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(f"{p.stem}.{os.getpid()}.partial.npz")
        np.savez(tmp, uv_a=m.uv_a, uv_b=m.uv_b, confidence=m.confidence, meta=np.array(meta))
        os.replace(tmp, p)
        return p

    def match(self, img_a: np.ndarray, img_b: np.ndarray, cfg: MatcherConfig | None = None,
              path_a: str | None = None, path_b: str | None = None) -> Matches:
        """Cached :func:`match_images`."""
        cfg = cfg or MatcherConfig()
        key, material = self.key(img_a, img_b, cfg, path_a, path_b)
        m = self.load(key)
        if m is not None:
            self.hits += 1
            return m
        self.misses += 1
        m = match_images(img_a, img_b, cfg)
        self.save(key, m, material)
        return m


def precompute_matches(samples: Iterable[Any], cfg: MatcherConfig, cache: MatchCache, progress: bool = True) -> int:
    """Fill the cache for every pair sample (``PairSample``); returns the number of view pairs done."""
    from tqdm import tqdm

    n = 0
    for s in tqdm(samples, desc="2D matches", disable=not progress):
        n += len(match_views(s.src_views, s.tgt_views, cfg, cache))
    return n


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m pcrcg.vision.matching data.root=DIR split=train views=3 cache_dir=cache/matches
    method=sift pairs=paper`` fills the match cache (the match dumps) for a data set."""
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
