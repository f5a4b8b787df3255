"""GeoTransformer's settings (``conf/model/geotransformer.yaml``), every radius in voxels of level 0.

The defaults are GeoTransformer's 3DMatch configuration (2.5 cm voxels, 4 levels): encoder
``init_dim`` 64 (``first_dim`` 128 here: level 0's width), fine features 256 wide at level 1,
superpoints at the coarsest level, transformer 256 wide with 4 heads and blocks
``self, cross`` x 3, ``sigma_d`` 0.2 m (8 voxels), ``sigma_a`` 15 deg, ``angle_k`` 3, 64 points
per patch, 100 Sinkhorn iterations, 128 superpoint targets in training (overlap > 0.1), 256
superpoint correspondences at test time, ground-truth matching radius 0.05 m (2 voxels), LGR
acceptance radius 0.1 m (4 voxels), top-3 mutual point matching above confidence 0.05, patches
with at least 3 correspondences, 5 refinement steps. Losses: overlap-aware circle loss (margins
0.1 / 1.4, scale 24, positive overlap 0.1) and the point-matching loss (positive radius 0.05 m).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from pcrcg.errors import ConfigError
from pcrcg.fields import NodeSettings
from pcrcg.models.encoder import KPConvSettings


@dataclass
class GeoLossConfig(NodeSettings):
    """Loss settings (``model.loss``); ``positive_radius`` in voxels."""

    positive_margin: float = 0.1
    negative_margin: float = 1.4
    positive_optimal: float = 0.1
    negative_optimal: float = 1.4
    log_scale: float = 24.0
    positive_overlap: float = 0.1
    positive_radius: float = 2.0
    w_coarse: float = 1.0
    w_fine: float = 1.0


@dataclass
class GeoTransformerConfig(KPConvSettings):
    """Network, matching and registration sizes (see the module docstring; the encoder's in
    :class:`KPConvSettings`)."""

    output_dim: int | None = None  # None: 2 * first_dim
    hidden_dim: int = 256
    num_heads: int = 4
    blocks: Sequence[str] = ("self", "cross", "self", "cross", "self", "cross")
    sigma_d: float = 8.0
    sigma_a: float = 15.0
    angle_k: int = 3
    patch_points: int | None = None  # None: 4 ** (num_layers - 1)
    sinkhorn_iterations: int = 100
    num_targets: int = 128
    target_overlap: float = 0.1
    num_correspondences: int = 256
    dual_normalization: bool = True
    matching_radius: float = 2.0
    topk: int = 3
    mutual: bool = True
    confidence_threshold: float = 0.05
    correspondence_threshold: int = 3
    acceptance_radius: float = 4.0
    refinement_steps: int = 5
    # MB of geometric structure embeddings kept in inference (a fragment's, for its other pairs); 0: none,
    # None: pcrcg.models.geotransformer.embedding.EMBEDDING_MEMO_BYTES. Changes no result (not hashed)
    embedding_memo_mb: int | None = None
    loss: GeoLossConfig = field(default_factory=GeoLossConfig)

    def __post_init__(self) -> None:
        if self.output_dim is None:
            self.output_dim = 2 * int(self.first_dim)
        if self.patch_points is None:
            self.patch_points = 4 ** (int(self.num_layers) - 1)

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], **overrides: Any) -> "GeoTransformerConfig":
        """From the ``model`` config node (keys of other models are ignored)."""
        kw = cls.known(m, **overrides)
        kw["loss"] = kw["loss"] if isinstance(kw.get("loss"), GeoLossConfig) else GeoLossConfig.from_mapping(kw.get("loss"))
        if "blocks" in kw:
            kw["blocks"] = tuple(kw["blocks"])
        cfg = cls(**kw)
        cfg.validate()
        return cfg

    @property
    def fine_level(self) -> int:
        return 1

    def validate(self) -> None:
        if self.num_layers < 3:
            raise ConfigError("model.num_layers", self.num_layers,
                              "an integer >= 3 (GeoTransformer: fine level 1, superpoints at the coarsest)")
        if self.first_dim % 4 or self.first_dim < 8:
            raise ConfigError("model.first_dim", self.first_dim, "a multiple of 4, >= 8")
        if self.hidden_dim % self.num_heads:
            raise ConfigError("model.num_heads", self.num_heads, f"a divisor of hidden_dim={self.hidden_dim}")
        if self.hidden_dim % 2:
            raise ConfigError("model.hidden_dim", self.hidden_dim, "an even integer (sinusoidal embedding)")
        for b in self.blocks:
            if b not in ("self", "cross"):
                raise ConfigError("model.blocks", list(self.blocks), "a list of 'self' / 'cross'")
        for name in ("patch_points", "sinkhorn_iterations", "num_targets", "num_correspondences", "topk",
                     "angle_k", "output_dim", "in_dim", "refinement_steps"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"model.{name}", getattr(self, name), "an integer >= 1")
        for name in ("sigma_d", "sigma_a", "matching_radius", "acceptance_radius", "voxel_size"):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"model.{name}", getattr(self, name), "a positive number")
        memo = self.embedding_memo_mb
        if memo is not None and (isinstance(memo, bool) or not isinstance(memo, (int, float)) or memo < 0):
            raise ConfigError("model.embedding_memo_mb", memo, "a number of megabytes >= 0 (0: no memo) or null")
        if not 0 <= self.target_overlap < 1:
            raise ConfigError("model.target_overlap", self.target_overlap, "a number in [0, 1)")
        if not float(self.loss.positive_radius) > 0:
            raise ConfigError("model.loss.positive_radius", self.loss.positive_radius, "a positive number")
