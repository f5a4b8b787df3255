"""2D pretraining of the ResUNet (Pri3D-style): ``python -m pcrcg.pretrain2d`` (config ``conf/pretrain2d.yaml``).

* :func:`pcrcg.pretrain2d.core.pretrain` ``(cfg, base_dir=None, log=print, progress=None) -> dict``: the
  whole run (data -> view pairs -> contrastive training -> held-out matching -> checkpoint -> MLflow).
* :mod:`pcrcg.pretrain2d.frames`: the RGB-D frames of a data set in the 3DMatch layout.
* The pure stages (correspondences, pair selection, InfoNCE, match accuracy) are in
  :mod:`pcrcg.vision.pretrain`.

The checkpoint is written with :func:`pcrcg.vision.encoders.save_pri3d_checkpoint`: a run loads it with
``encoder2d=pri3d encoder2d.weights=PATH`` (same ``encoder2d.arch``/``out_dim``/``decoder_channels``).
"""

from pcrcg.pretrain2d.core import check_settings, default_checkpoint, pretrain

__all__ = ["check_settings", "default_checkpoint", "pretrain"]
