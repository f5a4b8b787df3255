"""Registration: Predator's protocol (sampling, matching, RANSAC) and the classical baselines.

Public API
----------
* :class:`FragmentOutput` ``(points (N,3), descriptors (N,D), overlap (N,), matchability (N,))``
  and :func:`register_features` ``(src, tgt, n_points, cfg=RegistrationConfig(), seed) ->
  FeatureRegistration(transform, src_idx, tgt_idx, correspondences, ransac)``: one pair, one N.
* :class:`RegistrationConfig` ``(sampling="prob"|"topk"|"random", mutual=False,
  backend="torch"|"open3d", device="cpu", n_points=(5000, 2500, 1000, 500, 250), ransac=RansacConfig())``.
* :func:`sample_indices` ``(scores (N,), n, mode, rng) -> (n,) int64``.
* :func:`match_descriptors` ``(desc_src (N,D), desc_tgt (M,D), mutual=False, device=None) -> (K,2)``.
* :func:`ransac` ``(src_points (N,3), tgt_points (M,3), correspondences (K,2), cfg=RansacConfig(),
  seed=0, device=None) -> RansacResult(transform, fitness, inlier_rmse, n_inliers, iterations)``:
  our batched RANSAC; :func:`ransac_open3d` the same settings through Open3D (reference);
  :func:`ransac_feature_matching_open3d` Predator's Open3D call (KD-tree matching + RANSAC).
* Baselines (:mod:`pcrcg.registration.baselines`): :func:`register_pair` ``(method, src_points,
  tgt_points, *, src_colors, tgt_colors, src_views, tgt_views, init, cfg=BaselineConfig(), seed)
  -> BaselineResult(transform, ...)`` with ``method`` in ``fpfh | icp | color_icp | sift_dlt | sift_lifted``.

Every transform maps the source (fragment j of a ``gt.log`` entry ``i j``) into the target (i).
"""

from pcrcg.registration.baselines import (
    METHODS,
    BaselineConfig,
    BaselineResult,
    ColorIcpConfig,
    FpfhConfig,
    IcpConfig,
    SiftDltConfig,
    SiftLiftedConfig,
    lift_pixels,
    register_color_icp,
    register_fpfh,
    register_icp,
    register_pair,
    register_sift_dlt,
    register_sift_lifted,
)
from pcrcg.registration.matching import match_descriptors
from pcrcg.registration.feature_registration import (
    FeatureRegistration,
    FragmentOutput,
    RegistrationConfig,
    pair_seed,
    register_features,
)
from pcrcg.registration.ransac import (
    RansacConfig,
    RansacResult,
    kabsch,
    kabsch_numpy,
    ransac,
    ransac_feature_matching_open3d,
    ransac_open3d,
)
from pcrcg.registration.sampling import SAMPLING_MODES, sample_indices

__all__ = [
    "METHODS", "BaselineConfig", "BaselineResult", "ColorIcpConfig", "FpfhConfig", "IcpConfig", "SiftDltConfig",
    "SiftLiftedConfig", "lift_pixels", "register_color_icp", "register_fpfh", "register_icp", "register_pair",
    "register_sift_dlt", "register_sift_lifted",
    "match_descriptors", "FeatureRegistration", "FragmentOutput", "RegistrationConfig",
    "pair_seed", "register_features", "RansacConfig", "RansacResult", "kabsch", "kabsch_numpy", "ransac",
    "ransac_feature_matching_open3d", "ransac_open3d", "SAMPLING_MODES", "sample_indices",
]
