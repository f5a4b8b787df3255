"""Optimal transport with a dustbin (Sinkhorn in log space), as SuperGlue and GeoTransformer.

Scores (B, M, N) of M source and N target points per patch pair are padded with a learnable
dustbin score ``alpha`` into (B, M + 1, N + 1). With m, n the valid rows and columns of a patch
pair, the marginals are 1 for every valid point, n for the dustbin row and m for the dustbin
column (normalised by m + n while iterating, then scaled back), so ``exp`` of the result is a
soft assignment whose valid rows and columns each sum to 1. Invalid (padding) rows and columns
get a very negative log value (no probability) and never produce NaN gradients.

Two forms of the same iterations (:func:`log_optimal_transport` picks one):

* :func:`log_sinkhorn`, the reference: log-sum-exps over the whole (B, R, C) matrix, twice per
  iteration, each kept by autograd (100 iterations of a 450 x 450 coarse matrix: ~110 ms forward and
  as much backward on one CPU thread);
* :func:`scaling_sinkhorn`: ``K = exp(scores - max)`` once, then ``a = mu / (K b)``,
  ``b = nu / (K^T a)`` (matrix-vector products, no exponential in the loop), ``log a`` and ``log b``
  being the reference's potentials shifted by the constant max. Mathematically the same iterations
  and the same unrolled gradient; the results agree with the reference to float rounding
  (``tests/test_geotransformer.py``). It is used when the valid scores span at most
  :data:`SCALING_RANGE` of their dtype (so that no valid row of ``K`` underflows and the scalings stay
  finite), for float32 / float64 and unless the KPConv implementation is ``dense`` (the switch to the
  previous code, :mod:`pcrcg.models.kpconv.conv`); otherwise the reference runs.
"""

from __future__ import annotations

import torch
from torch import nn

from pcrcg.models.kpconv.conv import get_implementation

NEG = -1e9  # a finite "minus infinity": exp gives 0 and gradients stay finite
# largest span (max - min) of the valid scores of one matrix for which the scaling form runs: exp(-span)
# and the scalings (up to ~exp(span)) stay far inside the dtype's normal range
SCALING_RANGE = {torch.float32: 50.0, torch.float64: 500.0}


def log_sinkhorn(scores: torch.Tensor, log_mu: torch.Tensor, log_nu: torch.Tensor, iterations: int) -> torch.Tensor:
    """Sinkhorn iterations in log space: scores (B, R, C), log_mu (B, R), log_nu (B, C) -> (B, R, C)
    log transport plan with row sums exp(log_mu) and column sums exp(log_nu)."""
    u = torch.zeros_like(log_mu)
    v = torch.zeros_like(log_nu)
    for _ in range(int(iterations)):
        u = log_mu - torch.logsumexp(scores + v.unsqueeze(1), dim=2)
        v = log_nu - torch.logsumexp(scores + u.unsqueeze(2), dim=1)
    return scores + u.unsqueeze(2) + v.unsqueeze(1)


class _Scalings(torch.autograd.Function):
    """``(kernel (B, R, C), mu (B, R), nu (B, C), T) -> (a, b)``: T Sinkhorn scaling steps
    ``a = mu / (K b)``, ``b = nu / (K^T a)`` from ``b = 1``, with the exact unrolled gradient.

    The backward walks the T steps in reverse with matrix-vector products and forms the kernel's
    gradient ``sum_t outer(gx_t, b_{t-1}) + outer(a_t, gy_t)`` as two batched matrix products over
    the stacked iterates at the end, instead of 2T (B, R, C) outer products accumulated by autograd.
    A zero row / column sum (padding: its marginal is zero too) gives a zero scaling and no gradient."""

    @staticmethod
    def forward(ctx, kernel: torch.Tensor, mu: torch.Tensor, nu: torch.Tensor,  # type: ignore[override]
                iterations: int) -> tuple[torch.Tensor, torch.Tensor]:
        t_n = int(iterations)
        bsz, r, c = kernel.shape
        a_s = kernel.new_empty((t_n, bsz, r))
        x_s = kernel.new_empty((t_n, bsz, r))  # K b_{t-1}, zeros replaced by 1
        b_s = kernel.new_empty((t_n + 1, bsz, c))  # b_0 = 1, b_1 .. b_T
        y_s = kernel.new_empty((t_n, bsz, c))  # K^T a_t, zeros replaced by 1
        b_s[0] = 1.0
        for t in range(t_n):
            x = torch.bmm(kernel, b_s[t].unsqueeze(2)).squeeze(2)
            x_s[t] = x.masked_fill_(x <= 0, 1.0)
            torch.div(mu, x_s[t], out=a_s[t])
            y = torch.bmm(a_s[t].unsqueeze(1), kernel).squeeze(1)
            y_s[t] = y.masked_fill_(y <= 0, 1.0)
            torch.div(nu, y_s[t], out=b_s[t + 1])
        ctx.save_for_backward(kernel, a_s, x_s, b_s, y_s)
        return a_s[-1].clone(), b_s[-1].clone()

    @staticmethod
    def backward(ctx, g_a_out: torch.Tensor, g_b_out: torch.Tensor):  # type: ignore[override]
        kernel, a_s, x_s, b_s, y_s = ctx.saved_tensors
        t_n = a_s.shape[0]
        gx_s, gy_s = torch.empty_like(x_s), torch.empty_like(y_s)
        g_mu, g_nu = torch.zeros_like(a_s[0]), torch.zeros_like(b_s[0])
        g_b = g_b_out
        for t in range(t_n - 1, -1, -1):
            g_nu += g_b / y_s[t]  # b_{t+1} = nu / y_t
            gy_s[t] = -g_b * b_s[t + 1] / y_s[t]
            g_a = torch.bmm(kernel, gy_s[t].unsqueeze(2)).squeeze(2)  # y_t = K^T a_t
            if t == t_n - 1:
                g_a = g_a + g_a_out
            g_mu += g_a / x_s[t]  # a_t = mu / x_t
            gx_s[t] = -g_a * a_s[t] / x_s[t]
            g_b = torch.bmm(gx_s[t].unsqueeze(1), kernel).squeeze(1)  # x_t = K b_{t-1}
        # d/dK of x_t = K b_{t-1} and y_t = K^T a_t, summed over the steps (B, R, C)
        g_kernel = torch.einsum("tbr,tbc->brc", gx_s, b_s[:-1]) + torch.einsum("tbr,tbc->brc", a_s, gy_s)
        return g_kernel, g_mu, g_nu, None


def scaling_sinkhorn(scores: torch.Tensor, log_mu: torch.Tensor, log_nu: torch.Tensor, iterations: int) -> torch.Tensor:
    """:func:`log_sinkhorn`'s iterations in the scaling form: scores (B, R, C) with masked entries at
    :data:`NEG`, log_mu (B, R), log_nu (B, C) (masked: :data:`NEG`), iterations >= 1 -> (B, R, C) log
    transport plan. Padding rows / columns (zero marginal) get log values of about ``log(tiny)`` in
    place of the reference's arbitrary ones: callers mask them (:func:`log_optimal_transport`)."""
    shift = scores.detach().amax(dim=(1, 2), keepdim=True)  # (B, 1, 1): the largest valid score
    kernel = torch.exp(scores - shift)  # masked entries: exactly 0
    a, b = _Scalings.apply(kernel, torch.exp(log_mu), torch.exp(log_nu), int(iterations))
    tiny = torch.finfo(scores.dtype).tiny
    u = torch.log(a.clamp(min=tiny)) - shift.view(-1, 1)  # the reference's potentials
    v = torch.log(b.clamp(min=tiny))
    return scores + u.unsqueeze(2) + v.unsqueeze(1)


def _scaling_applies(padded: torch.Tensor, valid: torch.Tensor, iterations: int) -> bool:
    """Whether :func:`scaling_sinkhorn` may replace :func:`log_sinkhorn` on these scores (module docstring)."""
    limit = SCALING_RANGE.get(padded.dtype)
    if limit is None or iterations < 1 or get_implementation() == "dense" or padded.numel() == 0:
        return False
    with torch.no_grad():
        hi = padded.masked_fill(~valid, float("-inf")).amax(dim=(1, 2))
        lo = padded.masked_fill(~valid, float("inf")).amin(dim=(1, 2))
        return bool(((hi - lo) <= limit).all())


def log_optimal_transport(scores: torch.Tensor, alpha: torch.Tensor, row_mask: torch.Tensor, col_mask: torch.Tensor,
                          iterations: int) -> torch.Tensor:
    """scores (B, M, N), alpha () dustbin score, row_mask (B, M) / col_mask (B, N) bool (valid points)
    -> (B, M + 1, N + 1) log assignment (last row / column: the dustbins)."""
    b, m, n = scores.shape
    ones = row_mask.new_ones((b, 1))
    rows = torch.cat([row_mask, ones], 1)  # (B, M + 1)
    cols = torch.cat([col_mask, ones], 1)  # (B, N + 1)
    padded = torch.cat([torch.cat([scores, alpha.expand(b, m, 1)], 2), alpha.expand(b, 1, n + 1)], 1)
    valid = rows.unsqueeze(2) & cols.unsqueeze(1)
    padded = padded.masked_fill(~valid, NEG)
    n_rows = row_mask.sum(1).to(scores.dtype).clamp(min=1)
    n_cols = col_mask.sum(1).to(scores.dtype).clamp(min=1)
    norm = -torch.log(n_rows + n_cols)  # (B,)
    log_mu = torch.cat([norm.unsqueeze(1).expand(b, m), (torch.log(n_cols) + norm).unsqueeze(1)], 1)
    log_nu = torch.cat([norm.unsqueeze(1).expand(b, n), (torch.log(n_rows) + norm).unsqueeze(1)], 1)
    # a padding row / column carries (almost) no mass; its value stays finite
    log_mu = log_mu.masked_fill(~rows, NEG)
    log_nu = log_nu.masked_fill(~cols, NEG)
    sinkhorn = scaling_sinkhorn if _scaling_applies(padded, valid, iterations) else log_sinkhorn
    out = sinkhorn(padded, log_mu, log_nu, iterations) - norm.view(b, 1, 1)
    return out.masked_fill(~valid, NEG)


class LearnableOptimalTransport(nn.Module):
    """``forward(scores (B, M, N), row_mask, col_mask) -> (B, M + 1, N + 1)`` with a learned dustbin
    score (initialised at 1, as GeoTransformer)."""

    def __init__(self, iterations: int = 100):
        super().__init__()
        self.iterations = int(iterations)
        self.alpha = nn.Parameter(torch.tensor(1.0))

    def forward(self, scores: torch.Tensor, row_mask: torch.Tensor, col_mask: torch.Tensor) -> torch.Tensor:
        return log_optimal_transport(scores, self.alpha.to(scores.dtype), row_mask, col_mask, self.iterations)
