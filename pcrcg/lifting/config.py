"""Settings of the 2D->3D projection module (config groups ``projection`` and ``features``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from pcrcg.errors import ConfigError

PROJECTIONS = ("none", "implicit", "explicit")
COMBINE = ("overwrite", "mean")
WINDOW_STYLES = ("centred", "official")
FEATURES = ("none", "rgb", "sift", "deep", "disk")
VIEWS = (1, 2, 3)  # the first, last and middle frame of each fragment
_DEFAULT_DIM = {"none": 0, "rgb": 3, "sift": 32, "deep": 32, "disk": 32}


def check_official_window(projection: Any, window_style: Any, window_size: Any, key: str) -> None:
    """The official code's windows are ``2 * ((window_size - 1) // 2)`` pixels wide: none at 1. Raises
    :class:`ConfigError` naming ``key`` for an explicit projection with official windows below 3."""
    if projection == "explicit" and window_style == "official" and int(window_size or 0) < 3:
        raise ConfigError(key, window_size, "3 or more with projection.window_style=official "
                          "(its windows are 2 * ((window_size - 1) // 2) pixels wide: none at 1)")


@dataclass
class LiftingConfig:
    """What is lifted onto the points, from which views, and how.

    * ``projection``: ``none`` (no color: ``out_dim`` 0) | ``implicit`` (every pixel may be lifted) |
      ``explicit`` (only pixels within a ``window_size`` x ``window_size`` window centred on a 2D
      match, the feature scaled by the match confidence).
    * ``features``: ``none | rgb | sift | deep | disk``; ``feature_dim`` their width (``None``: 3 for rgb,
      32 for sift/deep/disk, 0 for none; rgb must be 3, sift and disk at most 128).
    * ``views``: 1..3, the first ``views`` of (first, last, middle) frame of each fragment.
    * ``window_size``: odd >= 1, pixels of the projection grid (explicit only).
    * ``window_style``: how a match's window is drawn (explicit only): ``centred`` (the paper's text: the
      ``window_size`` x ``window_size`` pixels centred on the rounded match pixel, the highest confidence
      where windows overlap) | ``official`` (the official code's slices ``[int(x - w), int(x + w))`` on both
      axes with ``w = (window_size - 1) // 2``, so 10 x 10 pixels for 11: its configs' ``window_size: 5``;
      in the matcher's order, a later match overwriting an earlier one; a window whose start falls below 0
      wraps to an empty slice, as NumPy's negative indices do there, and colors nothing).
    * ``depth_tolerance``: metres; a point takes a pixel only if ``|z_point - depth| < tolerance``.
    * ``image_size``: (H, W) of the projection grid (depth, feature maps, windows are resampled to
      it); ``None`` = each view's own resolution.
    * ``unseen_value``: the feature of a point that no selected view sees (outside every image, or
      its depth disagrees): 1.0 as the official code (its input is a constant 1 repeated to the full
      width there), 0.0 the project's first reading. A point that a view sees outside every window
      (explicit) gets 0 either way.
    * ``combine``: several views: ``overwrite`` as the official code (each view writes the points it
      sees, in reverse order of (first, last, middle), so the first-listed view that sees a point
      gives its value, even a 0 outside its windows) | ``mean`` (the average over the views whose
      weight is > 0, the paper's text).
    """

    projection: str = "explicit"
    features: str = "deep"
    views: int = 2
    window_size: int = 11
    depth_tolerance: float = 0.1
    feature_dim: int | None = None
    image_size: tuple[int, int] | None = None
    # the dataclass (and a config without these keys, e.g. an older checkpoint's) keeps the project's
    # first reading; conf/projection/*.yaml set the official code's (1.0, overwrite)
    unseen_value: float = 0.0
    combine: str = "mean"
    window_style: str = "centred"

    def __post_init__(self) -> None:
        if self.projection not in PROJECTIONS:
            raise ConfigError("projection.name", self.projection, " | ".join(PROJECTIONS))
        if self.features not in FEATURES:
            raise ConfigError("features.name", self.features, " | ".join(FEATURES))
        if isinstance(self.views, bool) or not isinstance(self.views, int) or self.views not in VIEWS:
            raise ConfigError("projection.views", self.views, "1, 2 or 3 (first, last, middle frame)")
        ws = self.window_size
        if isinstance(ws, bool) or not isinstance(ws, int) or ws < 1 or ws % 2 == 0:
            raise ConfigError("projection.window_size", ws, "an odd integer >= 1 (pixels)")
        if self.window_style not in WINDOW_STYLES:
            raise ConfigError("projection.window_style", self.window_style, " | ".join(WINDOW_STYLES))
        check_official_window(self.projection, self.window_style, ws, "projection.window_size")
        try:
            tol = float(self.depth_tolerance)
        except (TypeError, ValueError):
            tol = float("nan")
        if not tol > 0:
            raise ConfigError("projection.depth_tolerance", self.depth_tolerance, "metres > 0")
        self.depth_tolerance = tol
        if self.combine not in COMBINE:
            raise ConfigError("projection.combine", self.combine, " | ".join(COMBINE))
        try:
            self.unseen_value = float(self.unseen_value)
        except (TypeError, ValueError):
            raise ConfigError("projection.unseen_value", self.unseen_value, "a number (official: 1.0)") from None
        if self.feature_dim is None:
            self.feature_dim = _DEFAULT_DIM[self.features]
        if isinstance(self.feature_dim, bool) or not isinstance(self.feature_dim, int) or self.feature_dim < 0:
            raise ConfigError("features.dim", self.feature_dim, "an integer >= 0")
        if self.features == "rgb" and self.feature_dim != 3:
            raise ConfigError("features.dim", self.feature_dim, "3 for features=rgb")
        if self.features in ("sift", "deep", "disk") and self.feature_dim < 1:
            raise ConfigError("features.dim", self.feature_dim, f"an integer >= 1 for features={self.features}")
        if self.features in ("sift", "disk") and self.feature_dim > 128:
            raise ConfigError("features.dim", self.feature_dim, f"1..128 for features={self.features}")
        if self.image_size is not None:
            try:
                size = tuple(int(s) for s in self.image_size)
            except (TypeError, ValueError):
                size = ()
            if len(size) != 2 or min(size) < 1:
                raise ConfigError("projection.image_size", self.image_size, "null or [H, W] (pixels)")
            self.image_size = size  # type: ignore[assignment]

    @property
    def out_dim(self) -> int:
        """Width of the lifted features: 0 when nothing is lifted. The 3D input is ``1 + out_dim``."""
        if self.projection == "none" or self.features == "none":
            return 0
        return int(self.feature_dim)  # type: ignore[arg-type]

    @property
    def n_views_needed(self) -> int:
        """Views a data loader must provide (0 when nothing is lifted)."""
        return self.views if self.out_dim > 0 else 0

    @classmethod
    def from_cfg(cls, cfg: Any) -> "LiftingConfig":
        """From a root config holding ``projection`` and ``features`` nodes (DictConfig or dict)."""
        proj = _node(cfg, "projection")
        feat = _node(cfg, "features")
        size = proj.get("image_size")
        dim = feat.get("dim")
        return cls(
            projection=str(proj.get("name", "explicit")),
            features=str(feat.get("name", "deep")),
            views=_int(proj.get("views", 2), "projection.views"),
            window_size=_int(proj.get("window_size", 11), "projection.window_size"),
            depth_tolerance=proj.get("depth_tolerance", 0.1),
            feature_dim=None if dim is None else _int(dim, "features.dim"),
            image_size=None if size is None else tuple(size),
            unseen_value=proj.get("unseen_value", 0.0),
            combine=str(proj.get("combine", "mean")),
            window_style=str(proj.get("window_style", "centred")),
        )


def _int(v: Any, setting: str) -> int:
    if isinstance(v, bool):
        raise ConfigError(setting, v, "an integer")
    try:
        if float(v) != int(v):
            raise ValueError
        return int(v)
    except (TypeError, ValueError):
        raise ConfigError(setting, v, "an integer") from None


def _node(cfg: Any, key: str) -> dict[str, Any]:
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            sub = OmegaConf.select(cfg, key)
            return {} if sub is None else dict(OmegaConf.to_container(sub, resolve=True))  # type: ignore[arg-type]
    except ImportError:  # pragma: no cover
        pass
    if isinstance(cfg, Mapping):
        return dict(cfg.get(key) or {})
    return dict(getattr(cfg, key, None) or {})
