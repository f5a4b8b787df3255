"""Rigid kernel point convolution (KPConv) in plain PyTorch.

For a query q with support neighbours p_j (features f_j) and kernel points x_k (weights W_k):

    out(q) = (1 / n_q) * sum_j sum_k  max(0, 1 - |p_j - q - x_k| / extent) * f_j @ W_k

``n_q`` is the number of real (non-shadow) neighbours (Predator's normalisation; set
``normalize=False`` for the original KPConv sum).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from pcrcg.models.kpconv.kernel_points import kernel_points as make_kernel_points


def kpconv(
    q_pts: torch.Tensor,
    s_pts: torch.Tensor,
    neighbors: torch.Tensor,
    feats: torch.Tensor,
    kernel: torch.Tensor,
    weights: torch.Tensor,
    extent: float,
    normalize: bool = True,
) -> torch.Tensor:
    """Functional rigid KPConv with linear influence and sum aggregation.

    q_pts (M, 3), s_pts (N, 3), neighbors (M, H) long with shadow index N, feats (N, C),
    kernel (K, 3) relative to the query, weights (K, C, O) -> (M, O).
    """
    n_sup = s_pts.shape[0]
    # The shadow row has a zero feature, so its position never matters (no huge sentinel values:
    # they would overflow half precision).
    s_pad = torch.cat([s_pts, s_pts.new_zeros((1, 3))], 0)
    f_pad = torch.cat([feats, feats.new_zeros((1, feats.shape[1]))], 0)
    rel = s_pad[neighbors] - q_pts.unsqueeze(1)  # (M, H, 3)
    # |r - x|^2 = |r|^2 - 2 r.x + |x|^2, without materialising (M, H, K, 3)
    sq = (rel * rel).sum(-1, keepdim=True) - 2.0 * rel @ kernel.t() + (kernel * kernel).sum(-1)
    dist = torch.sqrt(torch.clamp(sq, min=0.0))  # (M, H, K)
    influence = torch.clamp(1.0 - dist / extent, min=0.0)
    neigh_f = f_pad[neighbors]  # (M, H, C)
    weighted = torch.matmul(influence.transpose(1, 2), neigh_f)  # (M, K, C)
    k, c, o = weights.shape
    out = weighted.reshape(-1, k * c) @ weights.reshape(k * c, o)
    if normalize:
        count = (neighbors < n_sup).sum(dim=1).clamp(min=1).to(out.dtype)
        out = out / count.unsqueeze(1)
    return out


class KPConv(nn.Module):
    """Rigid KPConv layer.

    ``radius`` scales the kernel disposition (KPConv's convolution radius; the disposition's mean
    radius is 0.66 of it), ``extent`` is the influence distance of a kernel point.
    """

    def __init__(self, in_channels: int, out_channels: int, radius: float, extent: float,
                 n_kernel_points: int = 15, kernel_seed: int = 0, normalize: bool = True):
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.radius, self.extent, self.normalize = float(radius), float(extent), normalize
        self.register_buffer("kernel", torch.from_numpy(make_kernel_points(n_kernel_points, radius, kernel_seed)))
        self.weights = nn.Parameter(torch.empty(n_kernel_points, in_channels, out_channels))
        bound = 1.0 / math.sqrt(in_channels * n_kernel_points)
        nn.init.uniform_(self.weights, -bound * math.sqrt(3.0), bound * math.sqrt(3.0))

    def forward(self, q_pts: torch.Tensor, s_pts: torch.Tensor, neighbors: torch.Tensor,
                feats: torch.Tensor) -> torch.Tensor:
        """q_pts (M, 3), s_pts (N, 3), neighbors (M, H), feats (N, C) -> (M, O)."""
        return kpconv(q_pts, s_pts, neighbors, feats, self.kernel, self.weights, self.extent, self.normalize)

    def extra_repr(self) -> str:
        return (f"in={self.in_channels}, out={self.out_channels}, radius={self.radius:.4f}, "
                f"extent={self.extent:.4f}, K={self.kernel.shape[0]}")
