"""The geometric transformer: self-attention with the geometric structure embedding interleaved
with cross-attention between the two clouds' superpoints.

Self-attention (multi-head, per head of width d): ``e_ij = (q_i . k_j + q_i . (r_ij W_P)) / sqrt(d)``
with r_ij the geometric embedding; cross-attention is plain multi-head attention to the other
cloud. Every layer: attention -> linear -> residual + LayerNorm, then a feed-forward block
(``dim -> 2 dim -> dim``, ReLU) -> residual + LayerNorm. One layer's weights serve both clouds.
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from pcrcg.models.geotransformer.embedding import GeometricStructureEmbedding
from pcrcg.models.kpconv.conv import get_implementation


def _heads(x: torch.Tensor, h: int) -> torch.Tensor:
    """(N, C) -> (h, N, C / h)."""
    return x.view(x.shape[0], h, -1).transpose(0, 1)


class _RelativeScores(torch.autograd.Function):
    """``torch.einsum("hnc,nmc->hnm", qw, pos)``: qw (h, N, C), pos (N, M, C) -> (h, N, M), the same values and
    gradients (bit for bit in float32 on the CPU, measured at the tests' and the cpu profile's sizes; pos's gradient
    to rounding in float64, where the einsum adds the heads in another order: ``tests/test_geotransformer.py``), with pos's gradient
    written in pos's (N, M, C) layout: the einsum's backward made it as (N, C, M) and copied it over, a pass of
    N * M * C floats (~125 MB at the cpu profile) for each self-attention layer and cloud of a training step."""

    @staticmethod
    def forward(ctx, qw: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(qw, pos)
        # per query n: (h, C) @ (C, M)
        return torch.bmm(qw.transpose(0, 1), pos.transpose(1, 2)).transpose(0, 1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        qw, pos = ctx.saved_tensors
        g = grad.permute(1, 2, 0).contiguous()  # (N, M, h)
        g_qw = torch.bmm(g.transpose(1, 2), pos).transpose(0, 1) if ctx.needs_input_grad[0] else None
        g_pos = torch.bmm(g, qw.transpose(0, 1)) if ctx.needs_input_grad[1] else None  # (N, M, h) @ (N, h, C)
        return g_qw, g_pos


class FeedForward(nn.Module):
    """x (N, C) -> LayerNorm(x + W2 relu(W1 x)), W1: C -> 2C."""

    def __init__(self, dim: int):
        super().__init__()
        self.expand, self.squeeze, self.norm = nn.Linear(dim, 2 * dim), nn.Linear(2 * dim, dim), nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(x + self.squeeze(F.relu(self.expand(x))))


class AttentionLayer(nn.Module):
    """Multi-head attention of ``x`` (N, C) to ``memory`` (M, C), optionally with a relative
    embedding ``pos`` (N, M, C) added to the keys of each query (GeoTransformer's RPE attention)."""

    def __init__(self, dim: int, num_heads: int, relative: bool):
        super().__init__()
        self.h = num_heads
        self.q, self.k, self.v = nn.Linear(dim, dim), nn.Linear(dim, dim), nn.Linear(dim, dim)
        self.p = nn.Linear(dim, dim) if relative else None
        self.out = nn.Linear(dim, dim)
        self.norm = nn.LayerNorm(dim)
        self.ffn = FeedForward(dim)

    def forward(self, x: torch.Tensor, memory: torch.Tensor, pos: torch.Tensor | None = None) -> torch.Tensor:
        n, c = x.shape
        d = c // self.h
        q, k, v = _heads(self.q(x), self.h), _heads(self.k(memory), self.h), _heads(self.v(memory), self.h)
        scores = q @ k.transpose(1, 2)  # (h, N, M)
        if self.p is not None and pos is not None:
            # q . (W_P r_nm + b_P) per head, without materialising the projected (N, M, C) embedding
            qw = torch.einsum("hnd,hdc->hnc", q, self.p.weight.view(self.h, d, -1))
            qb = (q * self.p.bias.view(self.h, 1, d)).sum(-1, keepdim=True)
            # the einsum under the KPConv implementation ``dense``, the switch to the previous code (benchmarks.model)
            rel = (torch.einsum("hnc,nmc->hnm", qw, pos) if get_implementation() == "dense"
                   else _RelativeScores.apply(qw, pos))
            scores = scores + rel + qb
        attn = torch.softmax(scores / d**0.5, dim=-1)
        msg = (attn @ v).transpose(0, 1).reshape(n, c)
        return self.ffn(self.norm(x + self.out(msg)))


class GeometricTransformer(nn.Module):
    """``forward(src_xyz (Ms, 3), tgt_xyz (Mt, 3), src (Ms, in_dim), tgt (Mt, in_dim))`` ->
    (Ms, out_dim), (Mt, out_dim) (not normalised). ``sigma_d`` in metres."""

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int, num_heads: int, blocks: Sequence[str],
                 sigma_d: float, sigma_a: float, angle_k: int):
        super().__init__()
        self.blocks = list(blocks)
        self.embedding = GeometricStructureEmbedding(hidden_dim, sigma_d, sigma_a, angle_k)
        self.in_proj = nn.Linear(in_dim, hidden_dim)
        self.layers = nn.ModuleList([AttentionLayer(hidden_dim, num_heads, relative=(b == "self"))
                                     for b in self.blocks])
        self.out_proj = nn.Linear(hidden_dim, out_dim)

    def forward(self, src_xyz: torch.Tensor, tgt_xyz: torch.Tensor, src: torch.Tensor,
                tgt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        src_pos, tgt_pos = self.embedding(src_xyz), self.embedding(tgt_xyz)
        src, tgt = self.in_proj(src), self.in_proj(tgt)
        for name, layer in zip(self.blocks, self.layers):
            if name == "self":
                src, tgt = layer(src, src, src_pos), layer(tgt, tgt, tgt_pos)
            else:
                src = layer(src, tgt)
                tgt = layer(tgt, src)
        return self.out_proj(src), self.out_proj(tgt)
