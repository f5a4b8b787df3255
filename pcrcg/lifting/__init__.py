"""The 2D->3D projection module (PCR-CG's contribution) and color coverage.

Public API
----------
* :class:`LiftingConfig` ``(projection="none"|"implicit"|"explicit", features="none"|"rgb"|"sift"|"deep"|"disk",
  views=1..3, window_size=odd >= 1, depth_tolerance=0.1 (m), feature_dim=None, image_size=None)``;
  bad values raise :class:`pcrcg.errors.ConfigError` naming the setting (``projection.window_size``,
  ``projection.views``, ``projection.name``, ``features.dim``, ...). ``LiftingConfig.from_cfg(cfg)``
  reads the Hydra nodes ``projection`` and ``features``. ``cfg.out_dim``: lifted width, 0 when
  ``projection=none`` or ``features=none``; ``cfg.n_views_needed``: views a loader must provide.
* :class:`ColorLifter` ``(cfg, extractor=None, matcher=None, match_cache=None)`` ``nn.Module``:

  - ``out_dim: int`` (fixed for a config; the 3D network's first layer takes ``1 + out_dim``);
  - ``forward(points (N, 3) tensor, views: list[View], weights=None, feature_maps=None)
    -> (features (N, out_dim) float32, covered (N,) bool)``; ``weights`` (explicit only): per view
    :class:`ViewKeypoints` (uv in the view's pixels + confidence), a (H, W) weight map on the
    projection grid, or None;
  - ``coverage(points, views, weights)`` -> covered (N,) bool without feature maps;
  - ``lift_pair(sample, matches=None)`` -> :class:`LiftedPair`.
* :func:`lift_pair` ``(lifter, sample: PairSample, matches={(a, b): Matches} | None, device=None)
  -> LiftedPair(src_feats, tgt_feats, src_covered, tgt_covered, color_coverage, n_matches)``;
  ``color_coverage`` = fraction of the points of *both* fragments that received a feature.
* :func:`pair_coverage` ``(lifter, sample, matches=None) -> float`` (no feature maps: cheap);
  :func:`pair_covered` ``(lifter, sample, matches=None) -> (src_covered (N,), tgt_covered (M,))`` bool.
* :func:`build_lifter` ``(cfg)`` from a root config with ``projection``, ``features``,
  ``encoder2d``, ``matcher2d``.
* :mod:`pcrcg.lifting.coverage`: ``coverage_sweep`` (views 1/2/3 and windows 3/7/11/17) and its CLI
  ``python -m pcrcg.lifting.coverage [data.root=DIR split=val n_pairs=8]``.
* the ray-cast RGB-D toy room the tests use is a fixture, :mod:`pcrcg.testing.scenes` (``make_pair``).

Semantics (see :mod:`pcrcg.lifting.projection`): a point takes a view's feature only when it
projects inside the image, in front of the camera, where the depth map agrees within
``depth_tolerance``; explicit projection keeps only pixels inside a ``window_size`` x ``window_size``
window centred on a 2D match and scales the feature by the match confidence; the features of the
views that cover a point are averaged; uncovered points get zeros. The gather is differentiable.
"""

from typing import Any

# The names below load on first use (PEP 562), so that pcrcg.lifting.config, which the config check imports,
# does not bring in torch with the projection module.
_FROM_CONFIG = ("FEATURES", "PROJECTIONS", "LiftingConfig")
_FROM_PROJECTION = (
    "ColorLifter",
    "LiftedPair",
    "ViewKeypoints",
    "build_lifter",
    "color_coverage",
    "keypoints_per_view",
    "lift_pair",
    "pair_coverage",
    "pair_covered",
    "project_points",
    "window_weight_map",
)


def __getattr__(name: str) -> Any:
    import importlib

    for module, names in (("config", _FROM_CONFIG), ("projection", _FROM_PROJECTION)):
        if name in names:
            return getattr(importlib.import_module(f"pcrcg.lifting.{module}"), name)
    raise AttributeError(f"module 'pcrcg.lifting' has no attribute {name!r}")


__all__ = [*_FROM_CONFIG, *_FROM_PROJECTION]
