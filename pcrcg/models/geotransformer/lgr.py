"""Point correspondences from the patch assignments and local-to-global registration (LGR).

* :func:`patch_correspondences`: in each superpoint correspondence, the point pairs that are among
  each other's ``k`` best assignments (mutual) with an assignment above ``threshold``;
* :func:`weighted_procrustes`: the weighted least-squares rigid motion (Kabsch with weights);
* :func:`local_to_global`: one hypothesis per superpoint correspondence (its own point pairs), the
  one with most inliers among all pairs wins, then ``steps`` rounds of re-fitting on its inliers.
  No RANSAC: the hypotheses come from the patches.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


def weighted_procrustes(src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None = None,
                        eps: float = 1e-8) -> torch.Tensor:
    """The rigid motion T minimising sum_i w_i |T src_i - tgt_i|^2.

    src, tgt (B, K, 3) or (K, 3), weights (B, K) / (K,) >= 0 (None: all 1) -> (B, 4, 4) / (4, 4).
    """
    single = src.dim() == 2
    if single:
        src, tgt = src.unsqueeze(0), tgt.unsqueeze(0)
        weights = None if weights is None else weights.unsqueeze(0)
    src64, tgt64 = src.double(), tgt.double()
    w = torch.ones(src.shape[:2], dtype=torch.float64, device=src.device) if weights is None else weights.double()
    w = w / (w.sum(1, keepdim=True) + eps)
    cs = (w.unsqueeze(2) * src64).sum(1, keepdim=True)
    ct = (w.unsqueeze(2) * tgt64).sum(1, keepdim=True)
    H = (src64 - cs).transpose(1, 2) @ (w.unsqueeze(2) * (tgt64 - ct))  # (B, 3, 3)
    U, _, Vh = torch.linalg.svd(H)
    V = Vh.transpose(1, 2)
    d = torch.sign(torch.linalg.det(V @ U.transpose(1, 2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], 1))
    R = V @ D @ U.transpose(1, 2)
    t = ct.squeeze(1) - (R @ cs.transpose(1, 2)).squeeze(2)
    T = torch.eye(4, dtype=torch.float64, device=src.device).repeat(src.shape[0], 1, 1)
    T[:, :3, :3], T[:, :3, 3] = R, t
    T = T.to(src.dtype)
    return T[0] if single else T


@torch.no_grad()
def patch_correspondences(log_assign: torch.Tensor, src_mask: torch.Tensor, tgt_mask: torch.Tensor, k: int,
                          threshold: float, mutual: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Point pairs of each patch pair from its assignment.

    log_assign (B, K+1, K+1) (dustbins last) or (B, K, K), src_mask (B, K), tgt_mask (B, K) ->
    (selected (B, K, K) bool, scores (B, K, K) = the assignment, zero where not selected).
    """
    kk = src_mask.shape[1]
    s = torch.exp(log_assign[:, :kk, :kk])
    kr, kc = min(k, s.shape[2]), min(k, s.shape[1])
    row_best = torch.zeros_like(s, dtype=torch.bool).scatter_(2, s.topk(kr, dim=2).indices, True)
    col_best = torch.zeros_like(s, dtype=torch.bool).scatter_(1, s.topk(kc, dim=1).indices, True)
    chosen = (row_best & col_best) if mutual else (row_best | col_best)
    chosen &= (s > threshold) & src_mask.unsqueeze(2) & tgt_mask.unsqueeze(1)
    return chosen, s * chosen


@dataclass
class LGRResult:
    """transform (4, 4) source -> target; the point pairs it used: src (C, 3), tgt (C, 3), scores (C,);
    inliers (C,) bool under the final transform; hypotheses: how many patches gave one."""

    transform: torch.Tensor
    src: torch.Tensor
    tgt: torch.Tensor
    scores: torch.Tensor
    inliers: torch.Tensor
    hypotheses: int


def _residual_inliers(T: torch.Tensor, src: torch.Tensor, tgt: torch.Tensor, radius: float) -> torch.Tensor:
    """T (H, 4, 4) or (4, 4), pairs (C, 3) -> (H, C) / (C,) bool: |T src - tgt| < radius."""
    moved = src @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]
    return torch.linalg.vector_norm(moved - tgt, dim=-1) < radius


@torch.no_grad()
def local_to_global(src: torch.Tensor, tgt: torch.Tensor, scores: torch.Tensor, group: torch.Tensor,
                    acceptance_radius: float, min_correspondences: int = 3, steps: int = 5) -> LGRResult:
    """LGR on point pairs src (C, 3) -> tgt (C, 3) with scores (C,) and ``group`` (C,) long, the
    superpoint correspondence each pair came from."""
    eye = torch.eye(4, dtype=src.dtype, device=src.device)
    if len(src) == 0:
        return LGRResult(eye, src, tgt, scores, torch.zeros(0, dtype=torch.bool, device=src.device), 0)
    ids, counts = torch.unique(group, return_counts=True)
    ids = ids[counts >= min_correspondences]
    weights = scores.clamp(min=0)
    if len(ids):
        # one weighted fit per patch pair, batched with zero-weight padding
        width = int(counts.max())
        member = group.unsqueeze(0) == ids.unsqueeze(1)  # (H, C)
        order = torch.argsort((~member).to(torch.int8), dim=1, stable=True)[:, :width]  # members first
        taken = torch.gather(member, 1, order)
        w = torch.where(taken, weights[order], torch.zeros((), dtype=weights.dtype, device=weights.device))
        hyps = weighted_procrustes(src[order], tgt[order], w)
        inl = _residual_inliers(hyps, src, tgt, acceptance_radius)  # (H, C)
        best = int(inl.sum(1).argmax())
        current = weights * inl[best].to(weights.dtype)
    else:
        T0 = weighted_procrustes(src, tgt, weights)
        current = weights * _residual_inliers(T0, src, tgt, acceptance_radius).to(weights.dtype)
    T = weighted_procrustes(src, tgt, current) if float(current.sum()) > 0 else eye
    for _ in range(max(0, int(steps) - 1)):
        current = weights * _residual_inliers(T, src, tgt, acceptance_radius).to(weights.dtype)
        if float(current.sum()) <= 0:
            break
        T = weighted_procrustes(src, tgt, current)
    return LGRResult(T, src, tgt, scores, _residual_inliers(T, src, tgt, acceptance_radius), int(len(ids)))
