"""GeoTransformer's geometric structure embedding: pair-wise distances and triplet-wise angles.

For superpoints p_i of one cloud, the embedding of the pair (i, j) is

    r_ij = W_D s(|p_i - p_j| / sigma_d) + max_x W_A s(angle(p_x - p_i, p_j - p_i) / sigma_a)

over the ``k`` nearest neighbours x of p_i, with ``s`` the sinusoidal embedding of a scalar. It
depends only on distances and angles, so it is invariant to a rigid motion of the cloud.

The (N, N, k, hidden_dim) tensors make it the GeoTransformer's costliest stage on a CPU (N: superpoints,
~550 per fragment at the cpu profile). :meth:`GeometricStructureEmbedding.forward` computes the formula
without them (:class:`_MaxOfProjections`): the projection of the sinusoidal embedding as two half-width
products (the weight's even columns take the sines, the odd ones the cosines), the max over the k angle
neighbours as a running maximum that remembers which neighbour won each channel, and a backward that
recomputes the sines and cosines and gives each channel's gradient to that neighbour (the first on
ties, as ``max``). :meth:`~GeometricStructureEmbedding.reference` is the formula as written, with
autograd; both give the same values and gradients to float rounding (the same products summed in
another order; ``tests/test_geotransformer.py``). Every pass runs on blocks of rows small enough to
stay in the CPU's cache: the embedding is memory-bound, not compute-bound (a pass over 10M floats
costs about what their sines cost).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict

import torch
from torch import nn


def sinusoidal_embedding(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Transformer-style embedding of scalars: x (...) -> (..., dim) with [sin, cos] interleaved
    at frequencies ``10000 ** (-2i / dim)``."""
    freq = torch.exp(torch.arange(0, dim, 2, device=x.device, dtype=x.dtype) * (-math.log(10000.0) / dim))
    phase = x.unsqueeze(-1) * freq  # (..., dim / 2)
    return torch.stack([torch.sin(phase), torch.cos(phase)], dim=-1).flatten(-2)


def _sines_cosines(x: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The two halves of :func:`sinusoidal_embedding`: x (...) -> sin, cos (..., dim / 2)."""
    freq = torch.exp(torch.arange(0, dim, 2, device=x.device, dtype=x.dtype) * (-math.log(10000.0) / dim))
    phase = x.unsqueeze(-1) * freq
    return torch.sin(phase), torch.cos(phase)


CHUNK_VALUES = 1 << 20  # sines (or cosines) per block of rows: ~4 MB in float32, so a block's passes stay in cache


def _row_blocks(rows: int, dim: int) -> list[slice]:
    step = max(1, CHUNK_VALUES // max(1, dim // 2))
    return [slice(a, min(rows, a + step)) for a in range(0, rows, step)]


class _MaxOfProjections(torch.autograd.Function):
    """``max_k linear(sinusoidal_embedding(x[..., k]))``: x (..., k) without gradient, weight (out, dim),
    bias (out,) -> (..., out), with gradients for the weight and the bias (module docstring). Rows are
    processed in blocks of ~1M sines so that every pass over a block stays in the CPU's cache."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None,  # type: ignore[override]
                dim: int) -> torch.Tensor:
        k, n_out = x.shape[-1], weight.shape[0]
        xr = x.reshape(-1, k)
        out = weight.new_empty((xr.shape[0], n_out))
        arg = torch.zeros((xr.shape[0], n_out), dtype=torch.uint8, device=x.device)
        w_sin, w_cos = weight[:, 0::2].t(), weight[:, 1::2].t()
        for rows in _row_blocks(xr.shape[0], dim):
            best = out[rows]
            for j in range(k):
                sin, cos = _sines_cosines(xr[rows, j], dim)
                y = torch.mm(sin, w_sin) if bias is None else torch.addmm(bias, sin, w_sin)
                y.addmm_(cos, w_cos)
                if j == 0:
                    best.copy_(y)
                else:
                    arg[rows].masked_fill_(y > best, j)  # strictly greater: the first maximum wins, as max
                    torch.maximum(best, y, out=best)
        ctx.save_for_backward(x, arg)
        ctx.dim, ctx.has_bias = dim, bias is not None
        return out.reshape(*x.shape[:-1], n_out)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        x, arg = ctx.saved_tensors
        dim, k, n_out = ctx.dim, x.shape[-1], grad.shape[-1]
        xr, g = x.reshape(-1, k), grad.reshape(-1, n_out)
        d_sin = grad.new_zeros((n_out, dim // 2))
        d_cos = grad.new_zeros((n_out, dim // 2))
        for rows in _row_blocks(xr.shape[0], dim):
            g_rows = g[rows]
            for j in range(k):
                sin, cos = _sines_cosines(xr[rows, j], dim)
                g_j = g_rows * (arg[rows] == j) if k > 1 else g_rows
                d_sin.addmm_(g_j.t(), sin)
                d_cos.addmm_(g_j.t(), cos)
        d_weight = torch.stack([d_sin, d_cos], dim=-1).reshape(n_out, dim)
        return None, d_weight, (g.sum(0) if ctx.has_bias else None), None


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


# memory for the embeddings memoised in inference (GeometricStructureEmbedding.memo_bytes), 2 GiB: at the cpu
# profile an embedding is 70-125 MB (550-700 superpoints x 64 channels), so ~16-30 fragments
EMBEDDING_MEMO_BYTES = 2 * 2**30


class GeometricStructureEmbedding(nn.Module):
    """``forward(points (N, 3)) -> (N, N, hidden_dim)``; ``sigma_d`` in metres, ``sigma_a`` in degrees.

    Without gradients (inference) the embedding is a function of the points and the weights alone, and a
    fragment's superpoints are the same in each of its pairs: the most recent embeddings are kept, up to
    ``memo_bytes`` (None: :data:`EMBEDDING_MEMO_BYTES`; 0: none), keyed by the points' bytes, and forgotten when
    the weights change (an optimiser step, ``load_state_dict``, ``.to()``). A kept embedding is the tensor the
    computation gave, so the outputs are those of computing it again, bit for bit; it is 78% of an inference
    at the cpu profile, and the 500 + 500 pairs a cpu-profile evaluation reads see each fragment ~3 times.
    """

    def __init__(self, hidden_dim: int, sigma_d: float, sigma_a: float, angle_k: int):
        super().__init__()
        self.dim, self.sigma_d, self.angle_k = hidden_dim, float(sigma_d), int(angle_k)
        self.factor_a = 180.0 / (float(sigma_a) * math.pi)
        self.proj_d = nn.Linear(hidden_dim, hidden_dim)
        self.proj_a = nn.Linear(hidden_dim, hidden_dim)
        self.memo_bytes: int | None = None  # GeoTransformer sets it from model.embedding_memo_mb
        self._memo: OrderedDict[tuple, torch.Tensor] = OrderedDict()
        self._memo_state: tuple = ()

    @torch.no_grad()
    def indices(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, N) scaled distances and (N, N, k) scaled angles: what the embedding reads."""
        dist = pairwise_distances(points)
        return dist / self.sigma_d, triplet_angles(points, self.angle_k, dist) * self.factor_a

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """points (N, 3) -> (N, N, hidden_dim): :meth:`reference`'s values and gradients, computed without
        the (N, N, k, hidden_dim) tensors (module docstring); memoised without gradients (class docstring)."""
        bound = EMBEDDING_MEMO_BYTES if self.memo_bytes is None else int(self.memo_bytes)
        if torch.is_grad_enabled() or bound <= 0:
            self.clear_memo()  # training: the weights are about to change; no memory held meanwhile
            return self._embed(points)
        return self._memoised(points, bound)

    def clear_memo(self) -> None:
        """Forget the kept embeddings (a benchmark that times one inference as a first sight of its fragments)."""
        self._memo.clear()

    def _weights_state(self) -> tuple:
        """Identifies the weights: each parameter's storage and in-place version, and the device."""
        return tuple((p.data_ptr(), p._version, str(p.device)) for p in self.parameters())

    def _memoised(self, points: torch.Tensor, bound: int) -> torch.Tensor:
        state = self._weights_state()
        if state != self._memo_state:
            self._memo.clear()
            self._memo_state = state
        data = points.detach().to("cpu").contiguous().numpy().tobytes()
        key = (tuple(points.shape), str(points.dtype), str(points.device), hashlib.blake2b(data, digest_size=16).digest())
        hit = self._memo.get(key)
        if hit is not None:
            self._memo.move_to_end(key)
            return hit
        out = self._embed(points)
        nbytes = lambda m: m.numel() * m.element_size()  # noqa: E731
        if nbytes(out) <= bound:
            self._memo[key] = out
            size = sum(nbytes(m) for m in self._memo.values())
            while size > bound:  # the oldest go first
                size -= nbytes(self._memo.popitem(last=False)[1])
        return out

    def _embed(self, points: torch.Tensor) -> torch.Tensor:
        d_idx, a_idx = self.indices(points)
        d_emb = _MaxOfProjections.apply(d_idx.unsqueeze(-1), self.proj_d.weight, self.proj_d.bias, self.dim)
        return d_emb + _MaxOfProjections.apply(a_idx, self.proj_a.weight, self.proj_a.bias, self.dim)

    def reference(self, points: torch.Tensor) -> torch.Tensor:
        """The formula as written: the interleaved embeddings, their projections, the max over k."""
        d_idx, a_idx = self.indices(points)
        d_emb = self.proj_d(sinusoidal_embedding(d_idx, self.dim))
        a_emb = self.proj_a(sinusoidal_embedding(a_idx, self.dim)).max(dim=2).values
        return d_emb + a_emb
