"""GeoTransformer's geometric structure embedding: pair-wise distances and triplet-wise angles.

For superpoints p_i of one cloud, the embedding of the pair (i, j) is

    r_ij = W_D s(|p_i - p_j| / sigma_d) + max_x W_A s(angle(p_x - p_i, p_j - p_i) / sigma_a)

over the ``k`` nearest neighbours x of p_i, with ``s`` the sinusoidal embedding of a scalar. It
depends only on distances and angles, so it is invariant to a rigid motion of the cloud.

The (N, N, k, hidden_dim) tensors make it the GeoTransformer's costliest stage on a CPU (N: superpoints,
~550 per fragment at the cpu profile). Without gradients (inference, evaluation),
:meth:`GeometricStructureEmbedding.forward` computes the formula without the interleaved embedding
(:func:`sinusoidal_linear`: the projection's even weight columns take the sines, the odd ones the
cosines) and takes the max over the k neighbours as a running elementwise maximum, one neighbour at a
time: the same values to float rounding (the same products summed in another order;
``tests/test_geotransformer.py``), 1.8 -> 1.4 s per cloud of 550 superpoints on one CPU thread. With
gradients it runs :meth:`~GeometricStructureEmbedding.reference`, the formula as written: the running
maximum's backward costs more than it saves (0.6 -> 1.5 s per cloud, measured).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


def sinusoidal_embedding(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Transformer-style embedding of scalars: x (...) -> (..., dim) with [sin, cos] interleaved
    at frequencies ``10000 ** (-2i / dim)``."""
    freq = torch.exp(torch.arange(0, dim, 2, device=x.device, dtype=x.dtype) * (-math.log(10000.0) / dim))
    phase = x.unsqueeze(-1) * freq  # (..., dim / 2)
    return torch.stack([torch.sin(phase), torch.cos(phase)], dim=-1).flatten(-2)


def sinusoidal_linear(x: torch.Tensor, linear: nn.Linear, dim: int) -> torch.Tensor:
    """``linear(sinusoidal_embedding(x, dim))``: x (...) -> (..., out), without the (..., dim) embedding
    (the sines meet the weight's even columns, the cosines its odd ones: the same terms, summed as two
    half-width products)."""
    freq = torch.exp(torch.arange(0, dim, 2, device=x.device, dtype=x.dtype) * (-math.log(10000.0) / dim))
    phase = x.unsqueeze(-1) * freq  # (..., dim / 2)
    w = linear.weight
    out = F.linear(torch.sin(phase), w[:, 0::2], linear.bias)
    return out + F.linear(torch.cos(phase), w[:, 1::2])


def pairwise_distances(points: torch.Tensor) -> torch.Tensor:
    """points (N, 3) -> (N, N) Euclidean distances (exact zeros on the diagonal)."""
    diff = points.unsqueeze(1) - points.unsqueeze(0)
    return torch.linalg.vector_norm(diff, dim=-1)


def triplet_angles(points: torch.Tensor, k: int, dist: torch.Tensor | None = None) -> torch.Tensor:
    """Angles (radians, in [0, pi]) between p_x - p_i and p_j - p_i for the ``k`` nearest neighbours
    x of each i: points (N, 3) -> (N, N, k') with k' = min(k, N - 1) (k' >= 1: a lone point uses itself)."""
    n = points.shape[0]
    dist = pairwise_distances(points) if dist is None else dist
    kk = max(1, min(k, n - 1))
    nn_idx = dist.topk(kk + 1 if n > 1 else 1, dim=1, largest=False).indices[:, -kk:]  # skip the point itself
    ref = points[nn_idx] - points.unsqueeze(1)  # (N, k, 3)
    anchor = points.unsqueeze(0) - points.unsqueeze(1)  # (N, N, 3): p_j - p_i
    cross = torch.linalg.vector_norm(torch.cross(ref.unsqueeze(1).expand(-1, n, -1, -1),
                                                 anchor.unsqueeze(2).expand(-1, -1, kk, -1), dim=-1), dim=-1)
    dot = torch.einsum("ikc,ijc->ijk", ref, anchor)
    return torch.atan2(cross, dot)


class GeometricStructureEmbedding(nn.Module):
    """``forward(points (N, 3)) -> (N, N, hidden_dim)``; ``sigma_d`` in metres, ``sigma_a`` in degrees."""

    def __init__(self, hidden_dim: int, sigma_d: float, sigma_a: float, angle_k: int):
        super().__init__()
        self.dim, self.sigma_d, self.angle_k = hidden_dim, float(sigma_d), int(angle_k)
        self.factor_a = 180.0 / (float(sigma_a) * math.pi)
        self.proj_d = nn.Linear(hidden_dim, hidden_dim)
        self.proj_a = nn.Linear(hidden_dim, hidden_dim)

    @torch.no_grad()
    def indices(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, N) scaled distances and (N, N, k) scaled angles: what the embedding reads."""
        dist = pairwise_distances(points)
        return dist / self.sigma_d, triplet_angles(points, self.angle_k, dist) * self.factor_a

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """points (N, 3) -> (N, N, hidden_dim): :meth:`reference` when gradients are recorded, else its
        values computed in less time and memory (module docstring)."""
        if torch.is_grad_enabled() and any(p.requires_grad for p in self.parameters()):
            return self.reference(points)
        d_idx, a_idx = self.indices(points)
        out = sinusoidal_linear(d_idx, self.proj_d, self.dim)
        a_emb = None
        for j in range(a_idx.shape[2]):  # the max over the k neighbours, one neighbour at a time
            y = sinusoidal_linear(a_idx[:, :, j], self.proj_a, self.dim)
            a_emb = y if a_emb is None else torch.maximum(a_emb, y)
        return out + a_emb

    def reference(self, points: torch.Tensor) -> torch.Tensor:
        """The formula as written: the interleaved embeddings, their projections, the max over k."""
        d_idx, a_idx = self.indices(points)
        d_emb = self.proj_d(sinusoidal_embedding(d_idx, self.dim))
        a_emb = self.proj_a(sinusoidal_embedding(a_idx, self.dim)).max(dim=2).values
        return d_emb + a_emb
