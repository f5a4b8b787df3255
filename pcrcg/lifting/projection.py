"""The 2D->3D projection module: lift per-pixel features of RGB-D views onto fragment points.

For each selected view (first, last, middle frame of the fragment):

1. points (fragment frame) -> camera frame with ``inverse(view.pose)`` -> pixel by the intrinsics
   (scaled to the projection grid), rounded to the nearest pixel centre;
2. a point *sees* the pixel when it is in front of the camera, inside the image, the depth map has a
   value there and ``|z - depth| < depth_tolerance`` (occluded points and holes get nothing);
3. ``implicit``: weight 1 for every seen pixel; ``explicit``: weight = the match confidence of the
   ``window_size`` x ``window_size`` window centred on a 2D match that holds the pixel (the highest
   when windows overlap; ``window_style=official``: the official code's slices, below), 0 outside every
   window;
4. the point's feature from that view is ``weight * feature_map[:, pixel]`` (a differentiable gather:
   gradients flow into the feature map, hence into the 2D encoder);
5. several views (``combine``): ``overwrite`` (the official code) takes the value of the first-listed
   view that sees the point (weight 0 outside its windows included); ``mean`` averages the views that
   cover it (weight > 0);
6. a point that no view sees gets ``unseen_value`` in every channel (1.0, the official code's constant),
   a point seen outside every window 0; ``covered`` (the coverage metric) = the feature came with a
   weight > 0.

The projection geometry runs in float64 without gradients; only the gather carries them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pcrcg.errors import ConfigError
from pcrcg.geometry import invert, scale_intrinsics
from pcrcg.lifting.config import LiftingConfig


@dataclass
class ViewKeypoints:
    """Pixels of one view that took part in 2D matches: ``uv`` (K, 2) (u, v) in the view's own
    image coordinates and their ``confidence`` (K,) in [0, 1]."""

    uv: np.ndarray
    confidence: np.ndarray

    def __post_init__(self) -> None:
        self.uv = np.asarray(self.uv, dtype=np.float32).reshape(-1, 2)
        self.confidence = np.asarray(self.confidence, dtype=np.float32).reshape(-1)

    def __len__(self) -> int:
        return len(self.confidence)


# --------------------------------------------------------------------------- pure functions


def grid_size(view: Any, image_size: Sequence[int] | None) -> tuple[int, int]:
    """(H, W) of the projection grid of a view."""
    if image_size is not None:
        return int(image_size[0]), int(image_size[1])
    h, w = view.depth.shape[:2]
    return int(h), int(w)


def grid_intrinsics(view: Any, size: tuple[int, int]) -> np.ndarray:
    """The view's intrinsics rescaled to the projection grid (pixel-centre convention)."""
    h, w = view.depth.shape[:2]
    if (h, w) == tuple(size):
        return np.asarray(view.intrinsics, dtype=np.float64)
    return scale_intrinsics(np.asarray(view.intrinsics, dtype=np.float64), size[1] / w, size[0] / h)


def grid_depth(view: Any, size: tuple[int, int], device: torch.device | str | None = None) -> torch.Tensor:
    """The view's depth map (H, W) float64 at the grid size (nearest pixel-centre resampling)."""
    d = torch.as_tensor(np.asarray(view.depth), dtype=torch.float64, device=device)
    if tuple(d.shape) == tuple(size):
        return d
    return F.interpolate(d[None, None], size=size, mode="nearest-exact")[0, 0]


def project_points(points: torch.Tensor, view: Any, size: tuple[int, int], depth_tolerance: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Which grid pixel each point sees in a view.

    points (N, 3) fragment frame (any float dtype, any device). Returns ``flat`` (N,) long pixel index
    ``v * W + u`` (0 where not visible) and ``visible`` (N,) bool.
    """
    dev = points.device
    with torch.no_grad():
        T = torch.as_tensor(invert(np.asarray(view.pose, dtype=np.float64)), dtype=torch.float64, device=dev)
        K = torch.as_tensor(grid_intrinsics(view, size), dtype=torch.float64, device=dev)
        p = points.detach().to(torch.float64)
        pc = p @ T[:3, :3].T + T[:3, 3]
        z = pc[:, 2]
        zs = torch.where(z > 1e-6, z, torch.ones_like(z))
        u = torch.round(K[0, 0] * pc[:, 0] / zs + K[0, 2])
        v = torch.round(K[1, 1] * pc[:, 1] / zs + K[1, 2])
        H, W = size
        inside = (z > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        ui = torch.where(inside, u, torch.zeros_like(u)).long()
        vi = torch.where(inside, v, torch.zeros_like(v)).long()
        flat = vi * W + ui
        d = grid_depth(view, size, dev).reshape(-1)[flat]
        visible = inside & (d > 0) & ((z - d).abs() < depth_tolerance)
        flat = torch.where(visible, flat, torch.zeros_like(flat))
    return flat, visible


def window_weight_map(uv: np.ndarray | torch.Tensor, confidence: np.ndarray | torch.Tensor, size: tuple[int, int],
                      window_size: int, device: torch.device | str | None = None, style: str = "centred") -> torch.Tensor:
    """(H, W) float32 weights of the windows around the match pixels ``uv`` (K, 2) (grid coordinates, u then v)
    with their ``confidence`` (K,); 0 outside every window.

    ``style="centred"``: each pixel takes the highest confidence of the ``window_size`` x ``window_size``
    windows centred on the rounded match pixels that contain it. ``style="official"``: the official code's
    windows, rows ``[int(v - w), int(v + w))`` and columns ``[int(u - w), int(u + w))`` with
    ``w = (window_size - 1) // 2`` as NumPy slices (a start below 0 wraps, and such a window is empty or
    clipped as NumPy makes it), written in the matches' order, a later one overwriting an earlier one."""
    H, W = size
    uv_np = uv.detach().cpu().numpy() if torch.is_tensor(uv) else np.asarray(uv)
    c_np = confidence.detach().cpu().numpy() if torch.is_tensor(confidence) else np.asarray(confidence)
    if style == "official":
        return _official_windows(uv_np.astype(np.float64).reshape(-1, 2), c_np.astype(np.float32).reshape(-1),
                                 size, window_size).to(device)
    if style != "centred":
        raise ValueError(f"window style {style!r}: centred | official")
    uv_t = torch.as_tensor(uv_np, dtype=torch.float32, device=device)
    c = torch.as_tensor(c_np, dtype=torch.float32, device=device)
    grid = torch.zeros(H * W, dtype=torch.float32, device=device)
    if len(c):
        u = torch.round(uv_t[:, 0]).long()
        v = torch.round(uv_t[:, 1]).long()
        ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        grid.scatter_reduce_(0, (v * W + u)[ok], c[ok], reduce="amax", include_self=True)
    grid = grid.view(1, 1, H, W)
    if window_size > 1:
        grid = F.max_pool2d(grid, kernel_size=window_size, stride=1, padding=window_size // 2)
    return grid[0, 0]


def _official_windows(uv: np.ndarray, confidence: np.ndarray, size: tuple[int, int], window_size: int) -> torch.Tensor:
    """The official code's weight map (``datasets/indoor.py``: ``map[int(x - w):int(x + w), int(y - w):int(y + w)]
    = confidence`` over a (W, H) array, match by match), here on the (H, W) grid: uv (K, 2) float64 -> (H, W)."""
    H, W = size
    w = (window_size - 1) // 2
    out = np.zeros((H, W), dtype=np.float32)
    for (u, v), c in zip(uv.tolist(), confidence.tolist()):
        out[int(v - w):int(v + w), int(u - w):int(u + w)] = c
    return torch.from_numpy(out)


def keypoints_to_grid(kp: ViewKeypoints, view: Any, size: tuple[int, int]) -> np.ndarray:
    """Keypoint pixels (K, 2) from the view's image coordinates to the projection grid."""
    h, w = view.color.shape[:2]
    sx, sy = size[1] / w, size[0] / h
    uv = kp.uv.astype(np.float64)
    return np.stack([(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5], 1)


def resample_map(fmap: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(C, h, w) feature map -> (C, H, W) (bilinear, pixel-centre aligned; identity if same size)."""
    if tuple(fmap.shape[-2:]) == tuple(size):
        return fmap
    return F.interpolate(fmap[None], size=size, mode="bilinear", align_corners=False)[0]


def keypoints_per_view(matches: Mapping[tuple[int, int], Any], n_src: int, n_tgt: int) -> tuple[list[ViewKeypoints], list[ViewKeypoints]]:
    """Per-view keypoints from pairwise matches ``{(a, b): Matches}`` (``uv_a`` in src view a,
    ``uv_b`` in tgt view b): the union over all pairs a view takes part in."""
    src: list[list] = [[] for _ in range(n_src)]
    tgt: list[list] = [[] for _ in range(n_tgt)]
    for (a, b), m in matches.items():
        if a < n_src:
            src[a].append((m.uv_a, m.confidence))
        if b < n_tgt:
            tgt[b].append((m.uv_b, m.confidence))

    def cat(lst: list) -> ViewKeypoints:
        if not lst:
            return ViewKeypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.float32))
        return ViewKeypoints(np.concatenate([x[0] for x in lst]), np.concatenate([x[1] for x in lst]))

    return [cat(x) for x in src], [cat(x) for x in tgt]


# --------------------------------------------------------------------------- the module


class ColorLifter(nn.Module):
    """The projection module built from a :class:`LiftingConfig`.

    ``extractor`` (:class:`pcrcg.vision.features.FeatureExtractor`) makes the feature maps; for
    ``features=rgb|sift`` one is built when omitted, for ``deep`` it must be given (it holds the
    encoder, a submodule here so that the 3D loss trains it). ``matcher`` / ``match_cache`` serve
    explicit projection in :meth:`lift_pair` when no matches are passed.
    """

    def __init__(self, cfg: LiftingConfig, extractor: nn.Module | None = None, matcher: Any = None,
                 match_cache: Any = None):
        super().__init__()
        self.cfg = cfg
        if extractor is None and cfg.out_dim > 0:
            from pcrcg.vision.features import FeatureExtractor

            if cfg.features == "deep":
                raise ConfigError("encoder2d", None, "an encoder (FeatureExtractor) for features=deep; use build_lifter(cfg)")
            extractor = FeatureExtractor(cfg.features, cfg.out_dim)
        if extractor is not None and cfg.out_dim > 0 and getattr(extractor, "out_dim", cfg.out_dim) != cfg.out_dim:
            raise ConfigError("features.dim", cfg.feature_dim, f"the feature extractor's width ({extractor.out_dim})")
        self.extractor = extractor if cfg.out_dim > 0 else None
        self.matcher = matcher
        self.match_cache = match_cache

    @property
    def out_dim(self) -> int:
        return self.cfg.out_dim

    # -- geometry ----------------------------------------------------------------------------

    def view_weights(self, points: torch.Tensor, view: Any, spec: Any = None) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int]]:
        """Pixel index (N,) long, weight (N,) float32 (0 = not covered) and grid size of one view."""
        flat, _, w, size = self.view_visibility(points, view, spec)
        return flat, w, size

    def view_visibility(self, points: torch.Tensor, view: Any, spec: Any = None
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[int, int]]:
        """Pixel index (N,) long, visible (N,) bool, weight (N,) float32 and grid size of one view."""
        size = grid_size(view, self.cfg.image_size)
        flat, visible = project_points(points, view, size, self.cfg.depth_tolerance)
        w = visible.to(torch.float32)
        if self.cfg.projection == "explicit":
            wmap = self._weight_map(view, spec, size, points.device)
            w = w * wmap.reshape(-1)[flat]
        return flat, visible, w, size

    def _weight_map(self, view: Any, spec: Any, size: tuple[int, int], device: torch.device) -> torch.Tensor:
        if spec is None:
            return torch.zeros(size, dtype=torch.float32, device=device)
        if isinstance(spec, ViewKeypoints) or (hasattr(spec, "uv") and hasattr(spec, "confidence")):
            kp = spec if isinstance(spec, ViewKeypoints) else ViewKeypoints(spec.uv, spec.confidence)
            return window_weight_map(keypoints_to_grid(kp, view, size), kp.confidence, size, self.cfg.window_size, device,
                                     self.cfg.window_style)
        wmap = torch.as_tensor(np.asarray(spec) if not torch.is_tensor(spec) else spec, device=device).float()
        if tuple(wmap.shape) != tuple(size):
            raise ValueError(f"weight map of shape {tuple(wmap.shape)} does not match the projection grid {size}")
        return wmap

    def _select(self, views: Sequence[Any], weights: Sequence[Any] | None) -> tuple[list, list]:
        n = self.cfg.views
        if len(views) < n:
            raise ValueError(f"{len(views)} views given but projection.views={n}: load the data with n_views >= {n}")
        views = list(views[:n])
        if self.cfg.projection == "explicit":
            if weights is None:
                raise ValueError("explicit projection needs per-view keypoints or weight maps (weights=...); "
                                 "use lift_pair() to match the views")
            weights = list(weights[:n]) + [None] * max(0, n - len(weights))
        else:
            weights = [None] * n
        return views, weights

    def coverage(self, points: torch.Tensor, views: Sequence[Any], weights: Sequence[Any] | None = None) -> torch.Tensor:
        """(N,) bool: which points would receive a feature (no feature maps computed)."""
        if self.cfg.projection == "none":
            return torch.zeros(len(points), dtype=torch.bool, device=points.device)
        views, weights = self._select(views, weights)
        cov = torch.zeros(len(points), dtype=torch.bool, device=points.device)
        if self.cfg.combine == "overwrite":  # the view that writes last (the first listed) decides
            for view, spec in reversed(list(zip(views, weights))):
                _, vis, w, _ = self.view_visibility(points, view, spec)
                cov = torch.where(vis, w > 0, cov)
            return cov
        for view, spec in zip(views, weights):
            _, w, _ = self.view_weights(points, view, spec)
            cov |= w > 0
        return cov

    # -- lifting -----------------------------------------------------------------------------

    def forward(self, points: torch.Tensor, views: Sequence[Any], weights: Sequence[Any] | None = None,
                feature_maps: Sequence[torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Lift features onto ``points`` (N, 3) (fragment frame).

        ``views``: the fragment's :class:`View` list (first, last, middle; the first ``cfg.views``
        are used). ``weights`` (explicit only): per view a :class:`ViewKeypoints` (or ``Matches``-like
        object with ``uv``/``confidence`` in the view's image coordinates), a (H, W) weight map on
        the projection grid, or None (the view lifts nothing). ``feature_maps``: precomputed
        (C, h, w) maps per view (else the extractor runs). Returns ``features (N, out_dim)`` float32
        and ``covered (N,)`` bool.
        """
        n = len(points)
        dev = points.device
        if self.out_dim == 0:
            return torch.zeros(n, 0, device=dev), torch.zeros(n, dtype=torch.bool, device=dev)
        views, weights = self._select(views, weights)
        maps = list(feature_maps[: len(views)]) if feature_maps is not None else self.extractor(views, dev)
        if len(maps) != len(views):
            raise ValueError(f"{len(maps)} feature maps for {len(views)} views")
        seen = torch.zeros(n, dtype=torch.bool, device=dev)
        if self.cfg.combine == "overwrite":
            # the official code: x[view_inds3d] = feature for each view in reverse order, so the
            # first-listed view that sees a point writes last and wins
            out = torch.zeros(n, self.out_dim, dtype=torch.float32, device=dev)
            covered = torch.zeros(n, dtype=torch.bool, device=dev)
            for view, spec, fmap in reversed(list(zip(views, weights, maps))):
                flat, vis, w, size = self.view_visibility(points, view, spec)
                f = resample_map(fmap.to(dev).float(), size).reshape(self.out_dim, -1)
                out = torch.where(vis[:, None], w[:, None] * f.index_select(1, flat).T, out)
                covered = torch.where(vis, w > 0, covered)
                seen |= vis
        else:
            acc = torch.zeros(n, self.out_dim, dtype=torch.float32, device=dev)
            count = torch.zeros(n, dtype=torch.float32, device=dev)
            for view, spec, fmap in zip(views, weights, maps):
                flat, vis, w, size = self.view_visibility(points, view, spec)
                f = resample_map(fmap.to(dev).float(), size).reshape(self.out_dim, -1)
                acc = acc + w[:, None] * f.index_select(1, flat).T
                count = count + (w > 0).float()
                seen |= vis
            covered = count > 0
            out = acc / count.clamp(min=1.0)[:, None]
        if self.cfg.unseen_value != 0.0:
            out = torch.where(seen[:, None], out, torch.full_like(out, self.cfg.unseen_value))
        return out, covered

    def match(self, sample: Any) -> dict:
        """2D matches between the selected views of a pair (``cfg.views`` of each fragment); the
        pair's ``transform`` (src -> tgt) serves ``matcher2d.pairs=covisible``."""
        from pcrcg.vision.matching import MatcherConfig, match_views

        cfg = self.matcher or MatcherConfig()
        n = self.cfg.views
        return match_views(sample.src_views[:n], sample.tgt_views[:n], cfg, self.match_cache,
                           getattr(sample, "transform", None))

    def lift_pair(self, sample: Any, matches: Mapping | None = None, device: torch.device | str | None = None) -> "LiftedPair":
        return lift_pair(self, sample, matches, device)


@dataclass
class LiftedPair:
    """Lifted features of a pair: ``src_feats`` (N, D), ``tgt_feats`` (M, D) float32 tensors,
    ``src_covered`` (N,), ``tgt_covered`` (M,) bool, ``color_coverage`` in [0, 1] (both fragments),
    ``n_matches`` (2D matches used; 0 unless explicit)."""

    src_feats: torch.Tensor
    tgt_feats: torch.Tensor
    src_covered: torch.Tensor
    tgt_covered: torch.Tensor
    color_coverage: float
    n_matches: int = 0


def color_coverage(src_covered: torch.Tensor | np.ndarray, tgt_covered: torch.Tensor | np.ndarray) -> float:
    """Fraction of the points of both fragments that received a feature."""
    s = int(np.asarray(src_covered.cpu() if torch.is_tensor(src_covered) else src_covered).sum())
    t = int(np.asarray(tgt_covered.cpu() if torch.is_tensor(tgt_covered) else tgt_covered).sum())
    n = len(src_covered) + len(tgt_covered)
    return (s + t) / n if n else 0.0


def pair_weights(lifter: ColorLifter, sample: Any, matches: Mapping | None) -> tuple[list | None, list | None, int]:
    """Per-view keypoints of src and tgt for explicit projection (matching when ``matches`` is None)."""
    if lifter.cfg.projection != "explicit":
        return None, None, 0
    n = lifter.cfg.views
    if matches is None:
        matches = lifter.match(sample)
    matches = {(a, b): m for (a, b), m in matches.items() if a < n and b < n}  # only the selected views
    src_kp, tgt_kp = keypoints_per_view(matches, min(n, len(sample.src_views)), min(n, len(sample.tgt_views)))
    return src_kp, tgt_kp, int(sum(len(m) for m in matches.values()))


def lift_pair(lifter: ColorLifter, sample: Any, matches: Mapping | None = None,
              device: torch.device | str | None = None) -> LiftedPair:
    """Lift features onto both fragments of a :class:`PairSample`.

    ``matches``: ``{(a, b): Matches}`` between ``sample.src_views[a]`` and ``sample.tgt_views[b]``
    (explicit projection; computed with ``lifter.matcher`` / ``lifter.match_cache`` when None).
    The views of both fragments go through the feature extractor in one batch.
    """
    dev = torch.device(device) if device is not None else _module_device(lifter)
    src_pts, tgt_pts = _as_points(sample.src_points, dev), _as_points(sample.tgt_points, dev)
    if lifter.out_dim == 0:
        zs, zt = lifter(src_pts, []), lifter(tgt_pts, [])
        return LiftedPair(zs[0], zt[0], zs[1], zt[1], 0.0, 0)
    src_w, tgt_w, n_matches = pair_weights(lifter, sample, matches)
    n = lifter.cfg.views
    sv, tv = list(sample.src_views[:n]), list(sample.tgt_views[:n])
    maps = lifter.extractor(sv + tv, dev)
    fs, cs = lifter(src_pts, sv, src_w, maps[: len(sv)])
    ft, ct = lifter(tgt_pts, tv, tgt_w, maps[len(sv):])
    return LiftedPair(fs, ft, cs, ct, color_coverage(cs, ct), n_matches)


def pair_covered(lifter: ColorLifter, sample: Any, matches: Mapping | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Which points of the pair's src (N,) and tgt (M,) would receive a feature (bool), without computing
    any feature map."""
    dev = _module_device(lifter)
    src_w, tgt_w, _ = pair_weights(lifter, sample, matches)
    cs = lifter.coverage(_as_points(sample.src_points, dev), sample.src_views, src_w)
    ct = lifter.coverage(_as_points(sample.tgt_points, dev), sample.tgt_views, tgt_w)
    return cs, ct


def pair_coverage(lifter: ColorLifter, sample: Any, matches: Mapping | None = None) -> float:
    """``color_coverage`` of a pair without computing any feature map (cheap, for sweeps)."""
    if lifter.cfg.projection == "none":
        return 0.0
    return color_coverage(*pair_covered(lifter, sample, matches))


def _as_points(x: Any, device: torch.device) -> torch.Tensor:
    """(N, 3) float32 tensor on ``device`` from a NumPy array or a tensor (no copy when already there)."""
    if torch.is_tensor(x):
        return x.to(device=device, dtype=torch.float32)
    return torch.as_tensor(np.asarray(x, dtype=np.float32), device=device)


def _module_device(m: nn.Module) -> torch.device:
    for p in m.parameters():
        return p.device
    return torch.device("cpu")


def build_lifter(cfg: Any, matcher_cache_dir: str | None = None) -> ColorLifter:
    """A :class:`ColorLifter` from a root config with ``projection``, ``features``, ``encoder2d``
    and ``matcher2d`` nodes (Hydra). The match cache lives in ``matcher2d.cache_dir`` (or
    ``matcher_cache_dir``); none when both are null. A ``runtime.device`` in ``cfg`` says where a
    learned matcher runs (else ``auto``: CUDA when torch has it)."""
    from pcrcg.vision.features import build_feature_extractor
    from pcrcg.vision.matching import MatchCache, MatcherConfig

    lcfg = LiftingConfig.from_cfg(cfg)
    get = (lambda k: _sel(cfg, k))
    extractor = None
    if lcfg.out_dim > 0:
        feat = dict(get("features") or {})
        feat.setdefault("name", lcfg.features)
        feat["dim"] = lcfg.out_dim
        extractor = build_feature_extractor(feat, get("encoder2d"))
    mnode = get("matcher2d")
    matcher = MatcherConfig.from_cfg(mnode) if mnode is not None else None
    runtime = get("runtime")
    device = runtime.get("device") if isinstance(runtime, Mapping) else None
    if matcher is not None and device in ("cpu", "cuda", "auto"):
        matcher.device = device
    cache_dir = matcher_cache_dir or (mnode or {}).get("cache_dir")
    cache = MatchCache(cache_dir) if cache_dir else None
    return ColorLifter(lcfg, extractor, matcher, cache)


def _sel(cfg: Any, key: str) -> Any:
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            node = OmegaConf.select(cfg, key)
            return None if node is None else OmegaConf.to_container(node, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    return cfg.get(key) if isinstance(cfg, Mapping) else getattr(cfg, key, None)
