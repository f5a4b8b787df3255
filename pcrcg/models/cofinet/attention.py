"""CoFiNet's attention block: SuperGlue-style attentional propagation, self and cross.

One layer updates ``x`` (B, N, C) from ``memory`` (B, M, C): multi-head attention (queries from
``x``, keys and values from ``memory``, scaled dot products, softmax) gives a message; the update is
``x + MLP([x, message])`` with ``MLP = Linear(2C, 2C) -> InstanceNorm -> ReLU -> Linear(2C, C)`` (last bias
zero at the start). Self layers attend within a cloud, cross layers to the other one (source first,
then the target from the updated source, as the official code). Padded points (node patches) are
left out of the keys and of the instance-norm statistics (the official code attends to its padding).
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn


def masked_instance_norm(x: torch.Tensor, mask: torch.Tensor | None, eps: float = 1e-5) -> torch.Tensor:
    """x (B, N, C) normalised per (batch, channel) over the valid points (``mask`` (B, N) bool or None),
    biased variance, no affine (``nn.InstanceNorm1d``'s defaults)."""
    if mask is None:
        mean = x.mean(1, keepdim=True)
        var = ((x - mean) ** 2).mean(1, keepdim=True)
    else:
        w = mask.unsqueeze(2).to(x.dtype)
        n = w.sum(1, keepdim=True).clamp(min=1)
        mean = (x * w).sum(1, keepdim=True) / n
        var = (((x - mean) ** 2) * w).sum(1, keepdim=True) / n
    return (x - mean) / torch.sqrt(var + eps)


class AttentionalPropagation(nn.Module):
    """``forward(x (B, N, C), memory (B, M, C), x_mask=None, memory_mask=None) -> (B, N, C)``."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.h = int(num_heads)
        self.q, self.k, self.v, self.merge = (nn.Linear(dim, dim) for _ in range(4))
        self.expand = nn.Linear(2 * dim, 2 * dim)
        self.squeeze = nn.Linear(2 * dim, dim)
        nn.init.zeros_(self.squeeze.bias)

    def forward(self, x: torch.Tensor, memory: torch.Tensor, x_mask: torch.Tensor | None = None,
                memory_mask: torch.Tensor | None = None) -> torch.Tensor:
        b, n, c = x.shape
        d = c // self.h
        split = lambda t: t.view(b, t.shape[1], self.h, d).transpose(1, 2)  # noqa: E731  (B, h, ., d)
        q, k, v = split(self.q(x)), split(self.k(memory)), split(self.v(memory))
        scores = q @ k.transpose(2, 3) / d**0.5  # (B, h, N, M)
        if memory_mask is not None:
            scores = scores.masked_fill(~memory_mask[:, None, None, :], -1e9)
        message = self.merge((torch.softmax(scores, dim=-1) @ v).transpose(1, 2).reshape(b, n, c))
        y = F.relu(masked_instance_norm(self.expand(torch.cat([x, message], 2)), x_mask))
        return x + self.squeeze(y)


class AttentionStack(nn.Module):
    """Self / cross layers in the order of ``blocks`` on both clouds, each layer's weights shared by
    the two: ``forward(src (B, Ns, C), tgt (B, Nt, C), src_mask=None, tgt_mask=None)``."""

    def __init__(self, dim: int, num_heads: int, blocks: Sequence[str]):
        super().__init__()
        self.blocks = list(blocks)
        self.layers = nn.ModuleList([AttentionalPropagation(dim, num_heads) for _ in self.blocks])

    def forward(self, src: torch.Tensor, tgt: torch.Tensor, src_mask: torch.Tensor | None = None,
                tgt_mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        for name, layer in zip(self.blocks, self.layers):
            if name == "self":
                src, tgt = layer(src, src, src_mask, src_mask), layer(tgt, tgt, tgt_mask, tgt_mask)
            else:
                src = layer(src, tgt, src_mask, tgt_mask)
                tgt = layer(tgt, src, tgt_mask, src_mask)
        return src, tgt
