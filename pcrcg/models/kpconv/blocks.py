"""KPConv network blocks (Predator / KPConv-FCNN style).

Every block takes ``(x, pyr)``: features (N_l, C) at its level and a :class:`TensorPyramid`
(points, neighbours, pools and upsamples per level of the stacked pair).
"""

from __future__ import annotations

import torch
from torch import nn

from pcrcg.models.kpconv.conv import KPConv, get_implementation
from pcrcg.models.kpconv.pyramid import TensorPyramid


def normalize_channels(x: torch.Tensor, dims: tuple[int, ...], eps: float) -> torch.Tensor:
    """``(x - mean) / sqrt(var + eps)`` with the biased variance and the mean over ``dims``.

    The reference (KPConv implementation ``dense``) takes them from ``torch.var_mean``, whose CPU
    reduction over leading dimensions runs at ~7 ns per element (3.3 ms for a 3800 x 128 input on
    one thread); the default takes two passes of sums (mean, then the mean of the squared
    deviations: as accurate, 3-10x faster, and a cheaper backward). The two agree to float rounding
    (``tests/test_speed_equivalence.py``)."""
    if get_implementation() == "dense":
        var, mean = torch.var_mean(x, dim=dims, unbiased=False, keepdim=True)
        return (x - mean) * torch.rsqrt(var + eps)
    if torch.is_grad_enabled() and x.requires_grad:
        return _NormalizeChannels.apply(x, dims, eps)
    return _normalize_forward(x, dims, eps)[0]


def _count(x: torch.Tensor, dims: tuple[int, ...]) -> int:
    """How many entries each channel's mean over ``dims`` averages."""
    n = 1
    for d in dims:
        n *= x.shape[d]
    return n


def _normalize_forward(x: torch.Tensor, dims: tuple[int, ...], eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(normalised x, 1 / std) by two passes of sums (:func:`normalize_channels`)."""
    n = _count(x, dims)
    dev = x - x.sum(dim=dims, keepdim=True) / n
    rstd = torch.rsqrt((dev * dev).sum(dim=dims, keepdim=True) / n + eps)
    return dev.mul_(rstd), rstd


class _NormalizeChannels(torch.autograd.Function):
    """:func:`normalize_channels` (the values of the two-pass formula, bit for bit) with the closed-form
    backward of a normalisation, dx = (g - mean(g) - y * mean(g * y)) / std (means over ``dims``), in
    place: about half the passes over the tensor of autograd's graph of the formula (float rounding
    only, ``tests/test_speed_equivalence.py``)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, dims: tuple[int, ...], eps: float) -> torch.Tensor:  # type: ignore[override]
        y, rstd = _normalize_forward(x, dims, eps)
        ctx.save_for_backward(y, rstd)
        ctx.dims = dims
        return y

    @staticmethod
    def backward(ctx, g: torch.Tensor):  # type: ignore[override]
        y, rstd = ctx.saved_tensors
        dims = ctx.dims
        n = _count(y, dims)
        mean_g = g.sum(dim=dims, keepdim=True) / n
        mean_gy = (g * y).sum(dim=dims, keepdim=True) / n
        gx = y * mean_gy
        gx.neg_().add_(g).sub_(mean_g).mul_(rstd)
        return gx, None, None


class PointNorm(nn.Module):
    """Per-channel normalisation over all points of the (stacked) cloud, no running statistics.

    x (N, C) -> (N, C). Predator normalises this way (an instance norm over the points), which
    behaves the same in training and evaluation and does not depend on the batch size.
    """

    def __init__(self, channels: int, eps: float = 1e-5, affine: bool = False):
        super().__init__()
        self.channels, self.eps = channels, eps
        if affine:
            self.weight = nn.Parameter(torch.ones(channels))
            self.bias = nn.Parameter(torch.zeros(channels))
        else:
            self.weight = self.bias = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = normalize_channels(x, (0,), self.eps)
        if self.weight is not None:
            y = y * self.weight + self.bias
        return y


class UnaryBlock(nn.Module):
    """Linear (no bias) -> PointNorm -> LeakyReLU(0.1) (no ReLU when ``relu=False``)."""

    def __init__(self, in_dim: int, out_dim: int, relu: bool = True):
        super().__init__()
        self.mlp = nn.Linear(in_dim, out_dim, bias=False)
        self.norm = PointNorm(out_dim)
        self.act = nn.LeakyReLU(0.1) if relu else nn.Identity()

    def forward(self, x: torch.Tensor, pyr: TensorPyramid | None = None) -> torch.Tensor:
        return self.act(self.norm(self.mlp(x)))


class LastUnaryBlock(nn.Module):
    """Final linear layer, no normalisation or activation."""

    def __init__(self, in_dim: int, out_dim: int):
        super().__init__()
        self.mlp = nn.Linear(in_dim, out_dim, bias=False)

    def forward(self, x: torch.Tensor, pyr: TensorPyramid | None = None) -> torch.Tensor:
        return self.mlp(x)


def _conv_inputs(pyr: TensorPyramid, layer: int, strided: bool):
    if strided:
        return pyr.points[layer + 1], pyr.points[layer], pyr.pools[layer]
    return pyr.points[layer], pyr.points[layer], pyr.neighbors[layer]


def max_pool_reference(x: torch.Tensor, inds: torch.Tensor) -> torch.Tensor:
    """Max of the features of each row of ``inds`` (shadow rows give 0): x (N, C), inds (M, H) -> (M, C).

    The plain autograd version (its backward builds an (M, H, C) zero tensor and scatters it back
    with an accumulating index_put); :func:`max_pool` computes the same."""
    x = torch.cat([x, x.new_zeros((1, x.shape[1]))], 0)
    return x[inds].max(dim=1).values


class _MaxOverDim1(torch.autograd.Function):
    """``x.max(dim=1).values`` with the values from ``amax`` (one vectorised pass: ~20x faster than
    the indexed reduction for (N, k, C) inputs on the CPU) and the indices found only for the
    backward, which is then autograd's own: the gradient goes to the first maximum."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(x)
        return x.amax(dim=1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        (x,) = ctx.saved_tensors
        idx = x.max(dim=1).indices.unsqueeze(1)
        return torch.zeros_like(x).scatter_(1, idx, grad.unsqueeze(1))


def max_over_neighbours(x: torch.Tensor) -> torch.Tensor:
    """Max over dim 1 of (N, k, C) -> (N, C): the values and gradient of ``x.max(dim=1).values``, bit
    for bit (the KPConv implementation ``dense`` runs that reference)."""
    if get_implementation() == "dense":
        return x.max(dim=1).values
    return _MaxOverDim1.apply(x)


def _gather_rows(x: torch.Tensor, inds: torch.Tensor) -> torch.Tensor:
    """The rows of ``x`` padded with a zero shadow row: x (N, C), inds (M, H) -> (M, H, C), the values of
    ``x_pad[inds]`` through ``index_select`` (~5x faster than advanced indexing on the CPU)."""
    x_pad = torch.cat([x, x.new_zeros((1, x.shape[1]))], 0)
    return x_pad.index_select(0, inds.reshape(-1)).view(*inds.shape, x.shape[1])


class _MaxPool(torch.autograd.Function):
    """Forward as :func:`max_pool_reference`; the backward adds each output's gradient to the support
    its maximum came from (the first maximum on ties, as autograd's max), without (M, H, C) tensors."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, inds: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        values, arg = _gather_rows(x, inds).max(dim=1)
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(inds.gather(1, arg))  # (M, C): the support of each maximum
            ctx.n = x.shape[0]
        return values

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        (src,) = ctx.saved_tensors
        out = grad.new_zeros((ctx.n + 1, grad.shape[1]))
        out.scatter_add_(0, src, grad)
        return out[:-1], None


def max_pool(x: torch.Tensor, inds: torch.Tensor) -> torch.Tensor:
    """Max of the features of each row of ``inds`` (shadow rows give 0): x (N, C), inds (M, H) -> (M, C).

    Same values and, to float rounding (the order of the additions), same gradient as
    :func:`max_pool_reference` (``tests/test_speed_equivalence.py``), which the KPConv implementation
    ``dense`` (the previous code, :func:`pcrcg.models.kpconv.conv.implementation`) uses."""
    if get_implementation() == "dense" or x.device.type != "cpu":
        # off the CPU the reference: scatter_add_ is non-deterministic on CUDA, index_put_ is not
        return max_pool_reference(x, inds)
    if not (torch.is_grad_enabled() and x.requires_grad):  # inference: the values only, in one pass
        return _gather_rows(x, inds).amax(dim=1)
    return _MaxPool.apply(x, inds)


class SimpleBlock(nn.Module):
    """KPConv (in -> out // 2) -> PointNorm -> LeakyReLU; the first block of the encoder."""

    def __init__(self, in_dim: int, out_dim: int, radius: float, extent: float, layer: int,
                 strided: bool = False, n_kernel_points: int = 15, kernel_seed: int = 0):
        super().__init__()
        self.layer, self.strided = layer, strided
        self.conv = KPConv(in_dim, out_dim // 2, radius, extent, n_kernel_points, kernel_seed)
        self.norm = PointNorm(out_dim // 2)
        self.act = nn.LeakyReLU(0.1)

    def forward(self, x: torch.Tensor, pyr: TensorPyramid) -> torch.Tensor:
        q, s, n = _conv_inputs(pyr, self.layer, self.strided)
        return self.act(self.norm(self.conv(q, s, n, x, pyr.cache)))


class ResnetBottleneckBlock(nn.Module):
    """unary(in -> out/4) -> KPConv(out/4) -> unary(out/4 -> out) + shortcut, LeakyReLU.

    Strided: the KPConv queries the next level's points through the pooling neighbours and the
    shortcut is a max-pool over the same neighbours.
    """

    def __init__(self, in_dim: int, out_dim: int, radius: float, extent: float, layer: int,
                 strided: bool = False, n_kernel_points: int = 15, kernel_seed: int = 0):
        super().__init__()
        self.layer, self.strided = layer, strided
        mid = out_dim // 4
        self.unary1 = UnaryBlock(in_dim, mid) if in_dim != mid else nn.Identity()
        self.conv = KPConv(mid, mid, radius, extent, n_kernel_points, kernel_seed)
        self.norm_conv = PointNorm(mid)
        self.unary2 = UnaryBlock(mid, out_dim, relu=False)
        self.shortcut = UnaryBlock(in_dim, out_dim, relu=False) if in_dim != out_dim else nn.Identity()
        self.act = nn.LeakyReLU(0.1)

    def forward(self, feats: torch.Tensor, pyr: TensorPyramid) -> torch.Tensor:
        q, s, n = _conv_inputs(pyr, self.layer, self.strided)
        x = self.unary1(feats)
        x = self.act(self.norm_conv(self.conv(q, s, n, x, pyr.cache)))
        x = self.unary2(x)
        short = max_pool(feats, n) if self.strided else feats
        return self.act(x + self.shortcut(short))


class NearestUpsampleBlock(nn.Module):
    """Features of level ``layer`` copied to level ``layer - 1`` from the nearest coarse point."""

    def __init__(self, layer: int):
        super().__init__()
        self.layer = layer

    def forward(self, x: torch.Tensor, pyr: TensorPyramid) -> torch.Tensor:
        x = torch.cat([x, x.new_zeros((1, x.shape[1]))], 0)
        return x[pyr.upsamples[self.layer - 1][:, 0]]
