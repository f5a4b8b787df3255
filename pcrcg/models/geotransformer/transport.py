"""Optimal transport with a dustbin (Sinkhorn in log space), as SuperGlue and GeoTransformer.

Scores (B, M, N) of M source and N target points per patch pair are padded with a learnable
dustbin score ``alpha`` into (B, M + 1, N + 1). With m, n the valid rows and columns of a patch
pair, the marginals are 1 for every valid point, n for the dustbin row and m for the dustbin
column (normalised by m + n while iterating, then scaled back), so ``exp`` of the result is a
soft assignment whose valid rows and columns each sum to 1. Invalid (padding) rows and columns
get a very negative log value (no probability) and never produce NaN gradients.
"""

from __future__ import annotations

import torch
from torch import nn

NEG = -1e9  # a finite "minus infinity": exp gives 0 and gradients stay finite


def log_sinkhorn(scores: torch.Tensor, log_mu: torch.Tensor, log_nu: torch.Tensor, iterations: int) -> torch.Tensor:
    """Sinkhorn iterations in log space: scores (B, R, C), log_mu (B, R), log_nu (B, C) -> (B, R, C)
    log transport plan with row sums exp(log_mu) and column sums exp(log_nu)."""
    u = torch.zeros_like(log_mu)
    v = torch.zeros_like(log_nu)
    for _ in range(int(iterations)):
        u = log_mu - torch.logsumexp(scores + v.unsqueeze(1), dim=2)
        v = log_nu - torch.logsumexp(scores + u.unsqueeze(2), dim=1)
    return scores + u.unsqueeze(2) + v.unsqueeze(1)


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
    out = log_sinkhorn(padded, log_mu, log_nu, iterations) - norm.view(b, 1, 1)
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
