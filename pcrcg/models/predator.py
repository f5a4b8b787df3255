"""Predator (Huang et al., CVPR 2021): KPConv encoder-decoder with overlap attention.

Architecture (as Predator's 3DMatch model, generalised to ``num_layers`` levels):

* encoder: ``simple``, ``resnetb`` at level 0; then per level ``resnetb_strided``, ``resnetb``,
  ``resnetb``; widths ``first_dim * 2**l``;
* bottleneck: linear to ``gnn_dim``, overlap attention (``self``: a DGCNN edge-conv on the
  k-nearest coarse points, ``cross``: multi-head attention to the other fragment, ``self``),
  a projection, a coarse overlap score and a cross-fragment "saliency" score (softmax over
  descriptor similarity with a learned temperature);
* decoder: nearest upsampling + unary blocks with skip connections; the last layer outputs
  ``final_dim`` descriptor channels plus an overlap and a matchability logit per point.

The input width ``in_dim`` is the only thing PCR-CG changes: 1 (a constant) + the lifted width.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn
from torch.profiler import record_function

from pcrcg.errors import ConfigError
from pcrcg.models.encoder import KPConvSettings, kpconv_encoder, run_encoder
from pcrcg.models.kpconv.blocks import (
    LastUnaryBlock,
    NearestUpsampleBlock,
    PointNorm,
    UnaryBlock,
    max_over_neighbours,
    normalize_channels,
)
from pcrcg.models.kpconv.conv import get_implementation
from pcrcg.models.kpconv.pyramid import TensorPyramid


@dataclass
class PredatorConfig(KPConvSettings):
    """Network sizes (the encoder's in :class:`KPConvSettings`). Radii are in units of ``voxel_size``
    (the level-0 grid), as in Predator."""

    final_dim: int = 32
    gnn_dim: int = 256
    num_heads: int = 4
    dgcnn_k: int = 10
    attention: Sequence[str] = field(default_factory=lambda: ("self", "cross", "self"))
    # not Predator's: each cross layer's MLP also reads how strongly a point matches the other fragment
    # (per head, the log-mean-exp of its attention logits there; :class:`CrossAttention`)
    cross_strength: bool = False

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], **overrides: Any) -> "PredatorConfig":
        """Build from a config mapping (unknown keys are ignored)."""
        kw = cls.known(m, **overrides)
        if "attention" in kw:
            kw["attention"] = tuple(kw["attention"])
        return cls(**kw)

    def validate(self) -> None:
        if self.num_layers < 2:
            raise ConfigError("model.num_layers", self.num_layers, "an integer >= 2")
        if self.first_dim % 4 or self.first_dim < 8:
            raise ConfigError("model.first_dim", self.first_dim, "a multiple of 4, >= 8")
        if self.gnn_dim % self.num_heads:
            raise ConfigError("model.num_heads", self.num_heads, f"a divisor of gnn_dim={self.gnn_dim}")
        for a in self.attention:
            if a not in ("self", "cross"):
                raise ConfigError("model.attention", list(self.attention), "a list of 'self' / 'cross'")
        if self.in_dim < 1:
            raise ConfigError("model.in_dim", self.in_dim, "an integer >= 1")


@dataclass
class PredatorOutput:
    """Per level-0 point of the stacked pair (source first): descriptors (N, D) L2-normalised,
    overlap / matchability probabilities (N,) and their logits (N,)."""

    descriptors: torch.Tensor
    overlap: torch.Tensor
    matchability: torch.Tensor
    overlap_logits: torch.Tensor
    matchability_logits: torch.Tensor
    # the bottleneck's own outputs, per coarse point of the stacked pair: overlap logit (Nc,) and the
    # features whose similarity carries the scores across (Nc, gnn_dim), unnormalised (coarse losses)
    coarse_logits: torch.Tensor | None = None
    coarse_feats: torch.Tensor | None = None


# --------------------------------------------------------------------------- attention


def knn_indices(coords: torch.Tensor, k: int) -> torch.Tensor:
    """The k nearest other points of each point: coords (N, 3) -> (N, k') long, k' = min(k, N - 1)."""
    n = coords.shape[0]
    k = max(0, min(k, n - 1))
    if k == 0:
        return torch.arange(n, device=coords.device).unsqueeze(1)
    d = torch.cdist(coords, coords)
    d.fill_diagonal_(float("inf"))
    return d.topk(k, dim=1, largest=False).indices


def edge_features(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """DGCNN edge features [x_i, x_j - x_i]: x (N, C), idx (N, k) -> (N, k, 2C)."""
    xi = x.unsqueeze(1).expand(-1, idx.shape[1], -1)
    return torch.cat([xi, x[idx] - xi], dim=-1)


def edge_linear(lin: nn.Linear, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``lin(edge_features(x, idx))`` for a bias-free ``lin`` (2C -> O), without the (N, k, 2C) edge tensor:
    with W = [Wa | Wb], W [x_i, x_j - x_i] = (Wa - Wb) x_i + Wb x_j = (A - B)_i + B_j, A = x Wa^T and
    B = x Wb^T per point (N x C x O multiply-adds instead of N x k x 2C x O), then one gather of B.
    The same sums in another order: equal to float rounding (``tests/test_speed_equivalence.py``)."""
    c = x.shape[1]
    w = lin.weight
    a = F.linear(x, w[:, :c])
    b = F.linear(x, w[:, c:])
    n, k = idx.shape
    return (a - b).unsqueeze(1) + b.index_select(0, idx.reshape(-1)).view(n, k, -1)


def _edge_norm(x: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    """Per-channel normalisation over all (point, neighbour) entries: (N, k, C) -> (N, k, C)."""
    return normalize_channels(x, (0, 1), eps)


class SelfAttentionGraph(nn.Module):
    """Predator's "self" layer: two edge-convolutions on the coordinate k-NN graph, then a fusion."""

    def __init__(self, dim: int, k: int = 10):
        super().__init__()
        self.k = k
        self.conv1 = nn.Linear(2 * dim, dim, bias=False)
        self.conv2 = nn.Linear(2 * dim, 2 * dim, bias=False)
        self.conv3 = nn.Linear(4 * dim, dim, bias=False)
        self.norm3 = PointNorm(dim)

    def forward(self, coords: torch.Tensor, x: torch.Tensor, idx: torch.Tensor | None = None) -> torch.Tensor:
        """coords (N, 3), x (N, C) -> (N, C); ``idx``: ``knn_indices(coords, self.k)`` when the caller has it.

        The KPConv implementation ``dense`` (the previous code, :func:`pcrcg.models.kpconv.implementation`)
        builds the (N, k, 2C) edge features and applies the convolutions to them; otherwise
        :func:`edge_linear` computes the same products per point (equal to float rounding)."""
        if idx is None:
            idx = knn_indices(coords, self.k)
        if get_implementation() == "dense":
            x1 = max_over_neighbours(F.leaky_relu(_edge_norm(self.conv1(edge_features(x, idx))), 0.2))
            x2 = max_over_neighbours(F.leaky_relu(_edge_norm(self.conv2(edge_features(x1, idx))), 0.2))
        else:
            x1 = max_over_neighbours(F.leaky_relu(_edge_norm(edge_linear(self.conv1, x, idx)), 0.2))
            x2 = max_over_neighbours(F.leaky_relu(_edge_norm(edge_linear(self.conv2, x1, idx)), 0.2))
        return F.leaky_relu(self.norm3(self.conv3(torch.cat([x, x1, x2], dim=-1))), 0.2)


class CrossAttention(nn.Module):
    """Multi-head attention of one fragment's points to the other's, then an MLP on [x, message].

    The softmax normalises the attention weights, so the message says what a point sees in the other
    fragment but not how well it matches there. With ``strength`` the MLP also reads, per head, the
    log-mean-exp of the point's attention logits over the other fragment (a soft maximum similarity, 0 for
    a point as similar to everything as to the mean): [x, message, strength] (not Predator's)."""

    def __init__(self, dim: int, num_heads: int, strength: bool = False):
        super().__init__()
        self.h = num_heads
        self.strength = bool(strength)
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(dim, dim)
        self.v = nn.Linear(dim, dim)
        self.merge = nn.Linear(dim, dim)
        self.mlp1 = nn.Linear(2 * dim + (num_heads if strength else 0), 2 * dim)
        self.norm = PointNorm(2 * dim)
        self.mlp2 = nn.Linear(2 * dim, dim)
        nn.init.zeros_(self.mlp2.bias)

    def forward(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        """x (N, C), source (M, C) -> message update (N, C)."""
        n, c = x.shape
        d = c // self.h
        q = self.q(x).view(n, self.h, d).transpose(0, 1)  # (h, N, d)
        k = self.k(source).view(-1, self.h, d).transpose(0, 1)  # (h, M, d)
        v = self.v(source).view(-1, self.h, d).transpose(0, 1)
        parts = [x]
        if not self.strength and source.shape[0] > 0 and get_implementation() != "dense":
            # torch's fused attention: the same softmax(q k^T / sqrt(d)) v without the (h, N, M) logits
            # and probabilities (float rounding only; the previous code under implementation dense)
            heads = F.scaled_dot_product_attention(q.unsqueeze(0), k.unsqueeze(0), v.unsqueeze(0)).squeeze(0)
            parts.append(self.merge(heads.transpose(0, 1).reshape(n, c)))
        else:
            logits = q @ k.transpose(1, 2) / d**0.5  # (h, N, M)
            attn = torch.softmax(logits, dim=-1)
            parts.append(self.merge((attn @ v).transpose(0, 1).reshape(n, c)))
            if self.strength:
                m = logits.shape[-1]
                parts.append((torch.logsumexp(logits, dim=-1) - math.log(max(m, 1))).transpose(0, 1))  # (N, h)
        return self.mlp2(F.relu(self.norm(self.mlp1(torch.cat(parts, dim=-1)))))


class OverlapAttention(nn.Module):
    """The bottleneck graph network: a sequence of ``self`` / ``cross`` layers over both fragments."""

    def __init__(self, dim: int, num_heads: int, k: int, layers: Sequence[str], cross_strength: bool = False):
        super().__init__()
        self.names = list(layers)
        self.layers = nn.ModuleList(
            [CrossAttention(dim, num_heads, cross_strength) if n == "cross" else SelfAttentionGraph(dim, k)
             for n in self.names]
        )

    def forward(self, src_xyz: torch.Tensor, tgt_xyz: torch.Tensor, src: torch.Tensor,
                tgt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        knn: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}  # the self layers' graphs, by k
        reuse = get_implementation() != "dense"  # the previous code built them in every layer
        for name, layer in zip(self.names, self.layers):
            if name == "cross":
                src = src + layer(src, tgt)
                tgt = tgt + layer(tgt, src)
            else:
                if layer.k not in knn or not reuse:
                    knn[layer.k] = (knn_indices(src_xyz, layer.k), knn_indices(tgt_xyz, layer.k))
                i_src, i_tgt = knn[layer.k]
                src, tgt = layer(src_xyz, src, i_src), layer(tgt_xyz, tgt, i_tgt)
        return src, tgt


# --------------------------------------------------------------------------- network


class Predator(nn.Module):
    """Predator on a stacked pair: ``forward(features (N0, in_dim), pyramid) -> PredatorOutput``."""

    def __init__(self, cfg: PredatorConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        L = cfg.num_layers
        self.encoder, self.layout = kpconv_encoder(cfg.in_dim, cfg.first_dim, L, cfg.voxel_size, cfg.conv_radius,
                                                   cfg.kp_extent, cfg.num_kernel_points, cfg.kernel_seed)
        dims = self.layout.dims
        self.skip_dims: list[int] = list(dims[:-1])

        g = cfg.gnn_dim
        self.bottle = nn.Linear(dims[-1], g)
        self.gnn = OverlapAttention(g, cfg.num_heads, cfg.dgcnn_k, cfg.attention, cfg.cross_strength)
        self.proj_gnn = nn.Linear(g, g)
        self.proj_score = nn.Linear(g, 1)
        self.epsilon = nn.Parameter(torch.tensor(-5.0))

        dec: list[nn.Module] = []
        x_dim = g + 2
        for j, level in enumerate(range(L - 1, 0, -1)):
            dec.append(NearestUpsampleBlock(level))
            in_dim = x_dim + self.skip_dims[level - 1]
            if level - 1 == 0:
                dec.append(LastUnaryBlock(in_dim, cfg.final_dim + 2))
            else:
                x_dim = (g + 2) // 2 ** (j + 1)
                dec.append(UnaryBlock(in_dim, x_dim))
        self.decoder = nn.ModuleList(dec)

    def forward(self, feats: torch.Tensor, pyr: TensorPyramid) -> PredatorOutput:
        """feats (N0, in_dim) for the stacked level-0 points of ``pyr`` -> per-point outputs."""
        if feats.shape[1] != self.cfg.in_dim:
            raise ValueError(f"features have {feats.shape[1]} channels, the model expects in_dim={self.cfg.in_dim}")
        with record_function("pcrcg.encoder (KPConv)"):
            x, skips = run_encoder(self.encoder, self.layout, feats, pyr)
        with record_function("pcrcg.attention (overlap attention)"):
            x, ns = self._bottleneck(x, pyr)
        g = self.cfg.gnn_dim
        coarse_logits, coarse_feats = x[:, 0], x[:, 2:2 + g]
        with record_function("pcrcg.decoder"):
            for block in self.decoder:
                if isinstance(block, NearestUpsampleBlock):
                    x = block(x, pyr)
                    x = torch.cat([x, skips.pop()], dim=1)
                else:
                    x = block(x, pyr)
        d = self.cfg.final_dim
        desc = F.normalize(x[:, :d], p=2, dim=1)
        ov_logit, m_logit = x[:, d], x[:, d + 1]
        return PredatorOutput(desc, torch.sigmoid(ov_logit), torch.sigmoid(m_logit), ov_logit, m_logit,
                              coarse_logits, coarse_feats)

    def _bottleneck(self, x: torch.Tensor, pyr: TensorPyramid) -> tuple[torch.Tensor, int]:
        """Overlap attention between the two fragments' coarse points -> (Nc, g + 2), n_src coarse."""
        ns, _ = pyr.split(-1)
        xyz = pyr.points[-1]
        x = self.bottle(x)
        src, tgt = self.gnn(xyz[:ns], xyz[ns:], x[:ns], x[ns:])
        x = self.proj_gnn(torch.cat([src, tgt], 0))
        score_c = self.proj_score(x)  # (Nc, 1)
        xn = F.normalize(x, p=2, dim=1)
        sim = xn[:ns] @ xn[ns:].t()
        temperature = torch.exp(self.epsilon) + 0.03
        s_src = torch.softmax(sim / temperature, dim=1) @ score_c[ns:]
        s_tgt = torch.softmax(sim.t() / temperature, dim=1) @ score_c[:ns]
        return torch.cat([score_c, torch.cat([s_src, s_tgt], 0), x], dim=1), ns


def build_predator(cfg: Mapping[str, Any] | PredatorConfig, in_dim: int | None = None) -> Predator:
    """Predator from a config mapping (``conf/model/predator.yaml``) or a :class:`PredatorConfig`."""
    return Predator(PredatorConfig.from_config(cfg, in_dim))
