"""CoFiNet's settings (``conf/model/cofinet.yaml``), every radius in voxels of level 0.

The defaults are CoFiNet's 3DMatch configuration (``configs/tdmatch/tdmatch.yaml`` of the official
code): 2.5 cm voxels, 4 levels, ``first_feats_dim`` 128, a 256-wide bottleneck and attention with 4
heads (self, cross, self), nodes at the coarsest level (20 cm), a decoder up to level 0 with 32-wide
fine features, 64 points per node patch (``neighbor_sel``), local attention in the patches (``acn``),
100 Sinkhorn iterations, 128 ground-truth node pairs per training pair (``corr_sel``), fine positives
within 0.1 m (4 voxels, ``pos_margin``), point correspondences within 3.75 cm (1.5 voxels,
``overlap_radius``) for the coarse ground truth; at test time the node pairs whose matching
probability exceeds 0.2, lowered until at least 200 pairs (``initial_thres``, ``min_coarse_corr``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from pcrcg.errors import ConfigError
from pcrcg.fields import NodeSettings
from pcrcg.models.encoder import KPConvSettings

BLOCKS = ("self", "cross")


@dataclass
class CoFiLossConfig(NodeSettings):
    """Loss weights (``model.loss``) and the level-0 correspondence radius of the data pipeline
    (``overlap_radius``, voxels), from which the coarse ground truth is made."""

    w_coarse: float = 1.0
    w_fine: float = 1.0
    overlap_radius: float = 1.5


@dataclass
class CoFiNetConfig(KPConvSettings):
    """Network, matching and registration sizes (see the module docstring; the encoder's in
    :class:`KPConvSettings`)."""

    gnn_dim: int = 256
    num_heads: int = 4
    final_dim: int = 32
    blocks: Sequence[str] = ("self", "cross", "self")
    local_attention: bool = True
    local_blocks: Sequence[str] = ("self", "cross", "self")
    patch_points: int | None = None  # None: 4 ** (num_layers - 1)
    sinkhorn_iterations: int = 100
    num_targets: int = 128
    target_overlap: float = 0.0
    positive_radius: float = 4.0
    coarse_threshold: float = 0.2
    min_coarse_correspondences: int = 200
    mutual: bool = False
    loss: CoFiLossConfig = field(default_factory=CoFiLossConfig)

    def __post_init__(self) -> None:
        if self.patch_points is None:
            self.patch_points = 4 ** (int(self.num_layers) - 1)

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], **overrides: Any) -> "CoFiNetConfig":
        """From the ``model`` config node (keys of other models are ignored)."""
        kw = cls.known(m, **overrides)
        kw["loss"] = kw["loss"] if isinstance(kw.get("loss"), CoFiLossConfig) else CoFiLossConfig.from_mapping(kw.get("loss"))
        for key in ("blocks", "local_blocks"):
            if key in kw:
                if isinstance(kw[key], str) or not isinstance(kw[key], Sequence):
                    raise ConfigError(f"model.{key}", kw[key], "a list of 'self' / 'cross'")
                kw[key] = tuple(kw[key])
        cfg = cls(**kw)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        def integer(name: str, low: int) -> int:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"model.{name}", v, f"an integer >= {low}")
            return v

        integer("num_layers", 2)
        if integer("first_dim", 2) % 2:
            raise ConfigError("model.first_dim", self.first_dim, "an even integer >= 2")
        for name in ("in_dim", "final_dim", "num_heads", "patch_points", "sinkhorn_iterations", "num_targets",
                     "min_coarse_correspondences"):
            integer(name, 1)
        step = 2 ** (self.num_layers - 2)  # the decoder halves the bottleneck width at every level up to level 1
        if integer("gnn_dim", 1) % self.num_heads:
            raise ConfigError("model.num_heads", self.num_heads, f"a divisor of gnn_dim={self.gnn_dim}")
        if self.gnn_dim % step:
            raise ConfigError("model.gnn_dim", self.gnn_dim, f"a multiple of 2^(num_layers-2)={step}")
        if self.local_attention and self.final_dim % self.num_heads:
            raise ConfigError("model.final_dim", self.final_dim,
                              f"a multiple of num_heads={self.num_heads} (local attention)")
        for key in ("blocks", "local_blocks"):
            v = getattr(self, key)
            if not v or any(b not in BLOCKS for b in v):
                raise ConfigError(f"model.{key}", list(v), "a non-empty list of 'self' / 'cross'")
        for name in ("voxel_size", "positive_radius"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ConfigError(f"model.{name}", v, "a positive number")
        for name in ("coarse_threshold", "target_overlap"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < 1:
                raise ConfigError(f"model.{name}", v, "a number in [0, 1)")
        for name in ("local_attention", "mutual"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"model.{name}", getattr(self, name), "true | false")
        for name in ("w_coarse", "w_fine", "overlap_radius"):
            v = getattr(self.loss, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0 or (name == "overlap_radius" and v == 0):
                raise ConfigError(f"model.loss.{name}", v, "a positive number" if name == "overlap_radius"
                                  else "a number >= 0")
