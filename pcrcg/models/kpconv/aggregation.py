"""KPConv's neighbour gather and kernel aggregation as one sparse matrix product (the fast CPU path).

The dense reference (:func:`pcrcg.models.kpconv.conv.kpconv`) gathers every query's padded
neighbour features into an (M, H, C) tensor and multiplies it by the (M, K, H) influences: the
gather and its scatter-add backward move M * H * C floats, and the product spends most of its
work on shadow neighbours (25-40% of the rows) and on kernel points out of reach (~58% of the
rest have zero influence).

The same sums are a linear map of the support features,

    weighted[m, k, :] = sum_h influence[m, h, k] * feats[neighbors[m, h], :]

that is one sparse matrix ``S`` of shape (K * M, N) holding the influences of the real (non-shadow)
neighbours only (zero influences are kept: compacting them away cost more than it saved here). :class:`KernelAggregation` builds ``S`` once per (queries, neighbours, kernel, extent)
and batch: every convolution of a level shares it, as they shared the influences. The forward is
``S @ feats`` and the backward ``S^T @ grad`` with a precomputed transpose (built on the first
backward), both MKL sparse-dense products on the CPU: no (M, H, C) tensor and no scatter-add.
Indices are int32 (what MKL takes: int64 ones were converted at every product). Measured at the
cpu profile on one thread: at level 0 of a pair (9.7k queries, 244k real neighbour pairs) building
``S`` with the influences takes 16-20 ms against 21-29 ms for the reference's influences alone, and
``S^T`` 12-20 ms; one convolution's forward + backward (6k queries, 8 channels) 8 ms against 15 ms.
On the CPU the integer work and the layout copies take NumPy's sort, mask and 16-bit radix argsort and
copies into preallocated (transposed) buffers: building ``S`` and ``S^T`` for every level of a cpu-profile
pair 60 -> 51 ms, and with three convolutions' forward + backward per geometry 301 -> 254 ms (20 training
pairs, one thread, Intel Xeon, 2026-12-07), the same integers and values bit for bit.

What is computed is unchanged: the influences are the reference's formula on the same numbers
(bit for bit), and a term dropped from a sum is an exact zero (a shadow's zero feature). Only the order in which the remaining terms are added differs, so outputs and
gradients agree with the reference to float rounding (``tests/test_speed_equivalence.py``).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch


def _csr(crow: torch.Tensor, col: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    with warnings.catch_warnings():  # "sparse CSR support is in beta": the product used here is stable
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, col, values, shape, check_invariants=False)


def influence_t(q_pts: torch.Tensor, s_pts: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor,
                kernel: torch.Tensor, extent: float) -> torch.Tensor:
    """Linear influences ``max(0, 1 - |s[cols] - q[rows] - x_k| / extent)`` of the pairs (rows, cols)
    as (K, E): :func:`pcrcg.models.kpconv.conv.kernel_influence`'s formula and rounding (the same
    operations in the same order: equal bit for bit), computed in place, on real neighbours only."""
    rel = s_pts.index_select(0, cols) - q_pts.index_select(0, rows)  # (E, 3)
    out = torch.mm(kernel, rel.t())  # (K, E): x_k . r
    # |r|^2 - 2 r.x + |x|^2 (-2 r.x is exact, so adding it is the reference's subtraction), clamp,
    # sqrt, 1 - d / extent (d / -extent is exactly -(d / extent)), clamp
    torch.add((rel * rel).sum(-1), out, alpha=-2.0, out=out)
    out.add_((kernel * kernel).sum(-1).unsqueeze(1))
    return out.clamp_(min=0.0).sqrt_().div_(-extent).add_(1.0).clamp_(min=0.0)


def _offsets(counts: torch.Tensor) -> torch.Tensor:
    out = counts.new_zeros(counts.numel() + 1)
    torch.cumsum(counts, 0, out=out[1:])
    return out


def _real_pairs_cpu(neighbors: torch.Tensor, n: int, idx: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The real (query, neighbour) pairs of ``neighbors`` (M, H) (shadow index ``n``), query-major and by
    neighbour index within a query: rows (E,) and cols (E,) in ``idx``, and count (M,) int64, the real
    neighbours per query. NumPy's sort, mask and repeat (~3x faster than torch's nonzero and division on one
    thread): the same integers as the device path."""
    nb = np.sort(neighbors.numpy(), axis=1)
    valid = nb < n
    count = valid.sum(axis=1, dtype=np.int64)
    np_idx = np.int32 if idx == torch.int32 else np.int64
    cols = nb[valid].astype(np_idx, copy=False)
    rows = np.repeat(np.arange(nb.shape[0], dtype=np_idx), count)
    return torch.from_numpy(rows), torch.from_numpy(cols), torch.from_numpy(count)


def _support_order(cols: torch.Tensor, n: int) -> torch.Tensor:
    """The real pairs by support, then query: the stable argsort of ``cols`` (E,) (values in [0, n)). On the CPU
    with n <= 65,536 NumPy's radix sort of 16-bit keys (~2.5x faster than torch's stable sort; a stable sort
    has one result, so the same permutation); elsewhere torch's."""
    if cols.device.type == "cpu" and n <= 2**16:
        return torch.from_numpy(np.argsort(cols.numpy().astype(np.uint16), kind="stable"))
    return torch.argsort(cols, stable=True)


class KernelAggregation:
    """The map feats (N, C) -> weighted (M, K * C) of one KPConv geometry, as a sparse matrix.

    q_pts (M, 3), s_pts (N, 3), neighbors (M, H) with shadow index N, kernel (K, 3), extent.
    ``count`` (M,): real neighbours per query (the normalisation). Positions get no gradient (as
    with the reference's cached influences: they are inputs).
    """

    def __init__(self, q_pts: torch.Tensor, s_pts: torch.Tensor, neighbors: torch.Tensor, kernel: torch.Tensor,
                 extent: float):
        with torch.no_grad():
            m, h = neighbors.shape
            k, n = kernel.shape[0], s_pts.shape[0]
            self.shape = (m, k, n)
            # int32 indices (what MKL takes: no conversion at every product) unless a size needs more
            idx = torch.int32 if max(k * m * h, n) < 2**31 - 1 else torch.int64
            # each query's neighbours by index (CSR rows want sorted columns); the shadow index n is the
            # largest, so real neighbours stay a prefix of every row
            if neighbors.device.type == "cpu":
                rows, cols, self.count = _real_pairs_cpu(neighbors, n, idx)
            else:
                nb = torch.sort(neighbors, dim=1).values
                valid = nb < n
                self.count = valid.sum(dim=1)
                flat = valid.reshape(-1).nonzero().squeeze(1)  # real (query, neighbour) pairs, query-major
                rows = torch.div(flat, h, rounding_mode="floor").to(idx)
                cols = nb.reshape(-1).index_select(0, flat).to(idx)
            infl = influence_t(q_pts, s_pts, rows, cols, kernel, extent)  # (K, E)
            self._infl_t, self._rows, self._cols = infl, rows, cols
            # S: row k * M + m holds query m's real neighbours with kernel point k's influence
            e_n = rows.numel()
            start = _offsets(self.count.to(idx))[:-1]
            crow = torch.cat([(torch.arange(k, dtype=idx, device=start.device).unsqueeze(1) * e_n
                               + start).reshape(-1), start.new_full((1,), k * e_n)])
            # the columns once per kernel point: a copy into a (K, E) buffer (~4x faster than ``repeat``)
            col = torch.empty((k, e_n), dtype=idx, device=cols.device)
            col.copy_(cols.expand(k, e_n))
            values = infl.reshape(-1)
            self._S = {values.dtype: _csr(crow, col.reshape(-1), values, (k * m, n))}
            self._St: dict[torch.dtype, torch.Tensor] = {}

    def forward_matrix(self, dtype: torch.dtype) -> torch.Tensor:
        """``S`` (K * M, N) in ``dtype``."""
        if dtype not in self._S:
            self._S[dtype] = next(iter(self._S.values())).to(dtype)
        return self._S[dtype]

    def backward_matrix(self, dtype: torch.dtype) -> torch.Tensor:
        """``S^T`` (N, M * K), columns ordered query-major (m * K + k), built on first use."""
        if not self._St:
            with torch.no_grad():
                m, k, n = self.shape
                cols, rows = self._cols, self._rows
                order = _support_order(cols, n).to(rows.dtype)  # int32 where the indices are: a faster gather
                e_n = rows.numel()
                col = torch.empty((e_n, k), dtype=rows.dtype, device=rows.device)
                torch.add((rows.index_select(0, order) * k).unsqueeze(1),
                          torch.arange(k, dtype=rows.dtype, device=rows.device), out=col)
                crow = _offsets(torch.bincount(cols, minlength=n).to(rows.dtype) * k)
                # the (K, E) rows gathered along E, then written transposed into an (E, K) buffer: the same
                # values as indexing the (E, K) transpose by rows (~3x faster: contiguous reads), and the copy
                # into a transposed view ~3x faster than ``.t().reshape(-1)``'s
                sel = self._infl_t.index_select(1, order)
                values = torch.empty((e_n, k), dtype=sel.dtype, device=sel.device)
                values.t().copy_(sel)
                values = values.reshape(-1)
                st = _csr(crow, col.reshape(-1), values, (n, m * k))
                self._St[st.dtype] = st
                self._infl_t = self._rows = self._cols = None  # only needed to build S^T
        if dtype not in self._St:
            self._St[dtype] = next(iter(self._St.values())).to(dtype)
        return self._St[dtype]

    def __call__(self, feats: torch.Tensor) -> torch.Tensor:
        """feats (N, C) -> (M, K * C), the product with the kernel-point influences."""
        return _Aggregate.apply(feats, self)


class _Aggregate(torch.autograd.Function):
    @staticmethod
    def forward(ctx, feats: torch.Tensor, agg: KernelAggregation) -> torch.Tensor:  # type: ignore[override]
        m, k, _ = agg.shape
        ctx.agg = agg
        out = agg.forward_matrix(feats.dtype) @ feats.contiguous()  # (K * M, C)
        c = feats.shape[1]
        if c == 1:  # (M, K) is a transposed view of (K, M): no copy
            return out.view(k, m).t()
        # kernel-major rows to query-major: a copy into a transposed view of the (M, K, C) result (~2x faster
        # than ``reshape``'s at C = 16-32 on one thread)
        res = out.new_empty((m, k, c))
        res.transpose(0, 1).copy_(out.view(k, m, c))
        return res.view(m, k * c)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        agg: KernelAggregation = ctx.agg
        m, k, _ = agg.shape
        if not ctx.needs_input_grad[0]:
            return None, None
        g = grad.contiguous().view(m * k, grad.shape[1] // k)
        return agg.backward_matrix(grad.dtype) @ g, None


def kpconv_sparse(feats: torch.Tensor, agg: KernelAggregation, weights: torch.Tensor,
                  normalize: bool = True) -> torch.Tensor:
    """The rigid KPConv of :func:`pcrcg.models.kpconv.conv.kpconv` through a :class:`KernelAggregation`:
    feats (N, C), weights (K, C, O) -> (M, O)."""
    k, c, o = weights.shape
    out = agg(feats) @ weights.reshape(k * c, o)
    if normalize:
        out = out / agg.count.clamp(min=1).to(out.dtype).unsqueeze(1)
    return out
