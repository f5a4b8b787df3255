"""Rigid kernel point convolution (KPConv) in plain PyTorch.

For a query q with support neighbours p_j (features f_j) and kernel points x_k (weights W_k):

    out(q) = (1 / n_q) * sum_j sum_k  max(0, 1 - |p_j - q - x_k| / extent) * f_j @ W_k

``n_q`` is the number of real (non-shadow) neighbours (Predator's normalisation; set
``normalize=False`` for the original KPConv sum).

Two implementations compute this sum (:func:`set_implementation` / :func:`implementation`):

* ``dense`` (:func:`kpconv`, the reference): gathers the padded neighbour features (M, H, C) and
  multiplies them by the influences (M, K, H);
* ``sparse`` (:mod:`pcrcg.models.kpconv.aggregation`): one sparse matrix of the non-shadow
  influences per level and batch, shared by the level's convolutions; the same sums in another
  order (outputs and gradients equal to float rounding), faster on the CPU.

``auto`` (the default) takes ``sparse`` for float32/float64 features on the CPU and ``dense``
elsewhere (GPUs, half precision, positions that require a gradient).

``dense`` is also the switch to the previous code of the other fast paths of the KPConv blocks,
so that one setting reproduces the old network step for comparisons
(``python -m pcrcg.benchmarks.model``): the max-pool's autograd backward
(:func:`pcrcg.models.kpconv.blocks.max_pool_reference`), ``torch.var_mean`` in the point and
edge normalisations (:func:`pcrcg.models.kpconv.blocks.normalize_channels`; otherwise two passes of
sums with a closed-form backward), Predator's attention (:class:`pcrcg.models.predator.SelfAttentionGraph`:
the (N, k, 2C) edge features and a k-NN graph per layer, instead of per-point products and shared graphs)
and its losses (:func:`pcrcg.models.losses.masked_circle_loss_reference` instead of the fused
log-sum-exps; the full score matrix of :func:`pcrcg.models.losses.matchability_labels`).
"""

from __future__ import annotations

import contextlib
import math
from typing import Iterator

import torch
from torch import nn
from torch.profiler import record_function

from pcrcg.models.kpconv.aggregation import KernelAggregation, kpconv_sparse
from pcrcg.models.kpconv.kernel_points import kernel_points as make_kernel_points

IMPLEMENTATIONS = ("auto", "sparse", "dense")
_IMPLEMENTATION = "auto"


def set_implementation(name: str) -> str:
    """Select how :class:`KPConv` layers compute (``auto`` | ``sparse`` | ``dense``, see the module
    docstring) for the whole process; returns the previous setting."""
    global _IMPLEMENTATION
    if name not in IMPLEMENTATIONS:
        raise ValueError(f"KPConv implementation {name!r}; known: {', '.join(IMPLEMENTATIONS)}")
    prev, _IMPLEMENTATION = _IMPLEMENTATION, name
    return prev


def get_implementation() -> str:
    return _IMPLEMENTATION


@contextlib.contextmanager
def implementation(name: str) -> Iterator[None]:
    """``with implementation("dense"): ...`` runs the block with that KPConv implementation."""
    prev = set_implementation(name)
    try:
        yield
    finally:
        set_implementation(prev)


def _use_sparse(name: str, q_pts: torch.Tensor, s_pts: torch.Tensor, feats: torch.Tensor) -> bool:
    if name == "dense":
        return False
    if q_pts.requires_grad or s_pts.requires_grad:  # the sparse path treats positions as constants
        return False
    if name == "sparse":
        return True
    return feats.device.type == "cpu" and feats.dtype in (torch.float32, torch.float64)


def kernel_influence(q_pts: torch.Tensor, s_pts: torch.Tensor, neighbors: torch.Tensor, kernel: torch.Tensor,
                     extent: float) -> torch.Tensor:
    """Linear influence ``max(0, 1 - |p_j - q - x_k| / extent)``: -> (M, H, K) (no gradient needed:
    positions are inputs). Shadow neighbours get arbitrary values; their features are zero."""
    # The shadow row sits at the origin: its feature is zero, so its position never matters (no huge
    # sentinel values, which would overflow half precision).
    s_pad = torch.cat([s_pts, s_pts.new_zeros((1, 3))], 0)
    rel = s_pad[neighbors] - q_pts.unsqueeze(1)  # (M, H, 3)
    # |r - x|^2 = |r|^2 - 2 r.x + |x|^2, without materialising (M, H, K, 3)
    sq = (rel * rel).sum(-1, keepdim=True) - 2.0 * rel @ kernel.t() + (kernel * kernel).sum(-1)
    return torch.clamp(1.0 - torch.sqrt(torch.clamp(sq, min=0.0)) / extent, min=0.0)


def kpconv(
    q_pts: torch.Tensor,
    s_pts: torch.Tensor,
    neighbors: torch.Tensor,
    feats: torch.Tensor,
    kernel: torch.Tensor,
    weights: torch.Tensor,
    extent: float,
    normalize: bool = True,
    influence: torch.Tensor | None = None,
) -> torch.Tensor:
    """Functional rigid KPConv with linear influence and sum aggregation.

    q_pts (M, 3), s_pts (N, 3), neighbors (M, H) long with shadow index N, feats (N, C),
    kernel (K, 3) relative to the query, weights (K, C, O) -> (M, O). ``influence`` (M, H, K):
    precomputed :func:`kernel_influence` (shared by the convolutions of a level).
    """
    n_sup = s_pts.shape[0]
    if influence is None:
        with record_function("pcrcg.kpconv.kernel_weights"):
            influence = kernel_influence(q_pts, s_pts, neighbors, kernel, extent)
    with record_function("pcrcg.kpconv.neighbour_gather"):
        f_pad = torch.cat([feats, feats.new_zeros((1, feats.shape[1]))], 0)
        neigh_f = f_pad[neighbors]  # (M, H, C)
    with record_function("pcrcg.kpconv.aggregate_and_weights"):
        weighted = torch.matmul(influence.transpose(1, 2).to(neigh_f.dtype), neigh_f)  # (M, K, C)
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
        kp = make_kernel_points(n_kernel_points, radius, kernel_seed)
        self.register_buffer("kernel", torch.from_numpy(kp))
        self._kernel_sig = kp.tobytes()  # identifies the disposition for the influence cache
        self.weights = nn.Parameter(torch.empty(n_kernel_points, in_channels, out_channels))
        bound = 1.0 / math.sqrt(in_channels * n_kernel_points)
        nn.init.uniform_(self.weights, -bound * math.sqrt(3.0), bound * math.sqrt(3.0))

    def forward(self, q_pts: torch.Tensor, s_pts: torch.Tensor, neighbors: torch.Tensor,
                feats: torch.Tensor, cache: dict | None = None) -> torch.Tensor:
        """q_pts (M, 3), s_pts (N, 3), neighbors (M, H), feats (N, C) -> (M, O).

        ``cache``: a dict living as long as the inputs (one batch); convolutions with the same
        neighbours, kernel and extent then share one influence tensor (``dense``) or one
        :class:`KernelAggregation` (``sparse``).
        """
        if _use_sparse(_IMPLEMENTATION, q_pts, s_pts, feats):
            key = ("sparse", id(neighbors), id(q_pts), self._kernel_sig, round(self.extent, 9))
            agg = cache.get(key) if cache is not None else None
            if agg is None:
                with record_function("pcrcg.kpconv.kernel_weights"):
                    agg = KernelAggregation(q_pts, s_pts, neighbors, self.kernel, self.extent)
                if cache is not None:
                    cache[key] = agg
            with record_function("pcrcg.kpconv.aggregate_and_weights"):
                return kpconv_sparse(feats, agg, self.weights, self.normalize)
        infl = None
        if cache is not None:
            key = ("dense", id(neighbors), id(q_pts), self._kernel_sig, round(self.extent, 9))
            infl = cache.get(key)
            if infl is None:
                with torch.no_grad(), record_function("pcrcg.kpconv.kernel_weights"):
                    infl = kernel_influence(q_pts, s_pts, neighbors, self.kernel, self.extent)
                cache[key] = infl
        return kpconv(q_pts, s_pts, neighbors, feats, self.kernel, self.weights, self.extent, self.normalize, infl)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[no-untyped-def]
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        k = state_dict.get(prefix + "kernel")
        if k is not None:
            self._kernel_sig = k.detach().to("cpu", torch.float32).numpy().tobytes()

    def extra_repr(self) -> str:
        return (f"in={self.in_channels}, out={self.out_channels}, radius={self.radius:.4f}, "
                f"extent={self.extent:.4f}, K={self.kernel.shape[0]}")
