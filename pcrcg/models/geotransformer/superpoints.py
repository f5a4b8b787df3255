"""Superpoints and their patches: partition, ground-truth overlaps, matching, training targets.

* :func:`point_to_node_partition`: every fine point goes to its nearest superpoint; a superpoint's
  patch is its ``k`` nearest fine points among those assigned to it (padded).
* :func:`patch_overlaps`: the ground-truth overlap of two patches, the mean over both patches of
  the share of their points within ``radius`` of the other patch (after the true motion).
* :func:`superpoint_matching`: the top correspondences of the dual-normalised feature correlation.
* :func:`sample_targets`: training pairs, ground-truth pairs with overlap above a threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Patches:
    """Patches of one cloud: ``indices`` (M, K) long into the fine points (padding: N), ``mask``
    (M, K) bool (real points), ``node_mask`` (M,) bool (superpoints that own at least one point)."""

    indices: torch.Tensor
    mask: torch.Tensor
    node_mask: torch.Tensor

    def points(self, fine: torch.Tensor) -> torch.Tensor:
        """The patches' points (M, K, 3), padding at the origin."""
        padded = torch.cat([fine, fine.new_zeros((1, 3))], 0)
        return padded[self.indices]


@torch.no_grad()
def point_to_node_partition(points: torch.Tensor, nodes: torch.Tensor, k: int) -> Patches:
    """points (N, 3) fine points, nodes (M, 3) superpoints, k points per patch -> :class:`Patches`."""
    n, m = points.shape[0], nodes.shape[0]
    k = max(1, min(int(k), n))
    d = torch.cdist(nodes, points)  # (M, N)
    owner = d.argmin(dim=0)  # (N,)
    node_mask = torch.zeros(m, dtype=torch.bool, device=points.device)
    node_mask[owner] = True
    foreign = owner.unsqueeze(0) != torch.arange(m, device=points.device).unsqueeze(1)
    d = d.masked_fill(foreign, float("inf"))
    dist, idx = d.topk(k, dim=1, largest=False)
    mask = torch.isfinite(dist)
    return Patches(idx.masked_fill(~mask, n), mask, node_mask)


def transform_points(T: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Rigid 4x4 (or batched (B, 4, 4)) applied to points (..., N, 3)."""
    T = T.to(pts.dtype)
    return pts @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


@torch.no_grad()
def patch_overlaps(src_nodes: torch.Tensor, tgt_nodes: torch.Tensor, src_fine: torch.Tensor, tgt_fine: torch.Tensor,
                   src_patches: Patches, tgt_patches: Patches, transform: torch.Tensor,
                   radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Ground-truth overlaps of every pair of patches that overlap at all.

    Nodes (Ms, 3) / (Mt, 3), fine points (Ns, 3) / (Nt, 3), ``transform`` (4, 4) source -> target,
    ``radius`` m -> (pairs (P, 2) long (source node, target node), overlaps (P,) in (0, 1]).
    """
    dev = src_nodes.device
    src_nodes = transform_points(transform, src_nodes)
    src_pts = transform_points(transform, src_patches.points(src_fine))  # (Ms, K, 3)
    tgt_pts = tgt_patches.points(tgt_fine)
    r_s = torch.where(src_patches.mask, torch.linalg.vector_norm(src_pts - src_nodes.unsqueeze(1), dim=-1),
                      src_pts.new_zeros(())).amax(1)
    r_t = torch.where(tgt_patches.mask, torch.linalg.vector_norm(tgt_pts - tgt_nodes.unsqueeze(1), dim=-1),
                      tgt_pts.new_zeros(())).amax(1)
    near = torch.cdist(src_nodes, tgt_nodes) < (r_s.unsqueeze(1) + r_t.unsqueeze(0) + radius)
    near &= src_patches.node_mask.unsqueeze(1) & tgt_patches.node_mask.unsqueeze(0)
    pairs = near.nonzero()
    if len(pairs) == 0:
        return pairs, src_pts.new_zeros(0)
    a, b = pairs[:, 0], pairs[:, 1]
    ma, mb = src_patches.mask[a], tgt_patches.mask[b]  # (P, K)
    d = torch.cdist(src_pts[a], tgt_pts[b])  # (P, K, K)
    close = (d < radius) & ma.unsqueeze(2) & mb.unsqueeze(1)
    share_s = close.any(2).sum(1).float() / ma.sum(1).clamp(min=1).float()
    share_t = close.any(1).sum(1).float() / mb.sum(1).clamp(min=1).float()
    overlap = 0.5 * (share_s + share_t)
    keep = overlap > 0
    return pairs[keep].to(dev), overlap[keep]


def dense_overlaps(pairs: torch.Tensor, overlaps: torch.Tensor, ms: int, mt: int) -> torch.Tensor:
    """Sparse overlaps -> (Ms, Mt) matrix (0 where the patches do not overlap)."""
    out = overlaps.new_zeros((ms, mt))
    if len(pairs):
        out[pairs[:, 0], pairs[:, 1]] = overlaps
    return out


@torch.no_grad()
def superpoint_matching(src_feats: torch.Tensor, tgt_feats: torch.Tensor, src_mask: torch.Tensor,
                        tgt_mask: torch.Tensor, k: int, dual: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Superpoint correspondences from unit features (Ms, C) / (Mt, C) and node masks.

    Scores s_ij = exp(-|f_i - g_j|^2), dual-normalised ``s_ij / sum_j s_ij * s_ij / sum_i s_ij``;
    the ``k`` highest -> (pairs (P, 2) long (source node, target node), scores (P,)), P = min(k, valid pairs).
    """
    si, ti = src_mask.nonzero().squeeze(1), tgt_mask.nonzero().squeeze(1)
    if len(si) == 0 or len(ti) == 0:
        return src_feats.new_zeros((0, 2), dtype=torch.long), src_feats.new_zeros(0)
    s = torch.exp(-(2.0 - 2.0 * src_feats[si] @ tgt_feats[ti].t()).clamp(min=0))
    if dual:
        s = (s / s.sum(1, keepdim=True)) * (s / s.sum(0, keepdim=True))
    k = min(int(k), s.numel())
    scores, flat = s.flatten().topk(k)
    rows, cols = flat // s.shape[1], flat % s.shape[1]
    return torch.stack([si[rows], ti[cols]], 1), scores


@torch.no_grad()
def sample_targets(pairs: torch.Tensor, overlaps: torch.Tensor, k: int, threshold: float,
                   generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Ground-truth superpoint pairs for training: those with overlap > ``threshold`` (all overlapping
    pairs when none is), at most ``k`` drawn at random -> (pairs (P, 2), overlaps (P,))."""
    keep = overlaps > threshold
    if not bool(keep.any()):
        keep = overlaps > 0
    pairs, overlaps = pairs[keep], overlaps[keep]
    if len(pairs) > k:
        pick = torch.randperm(len(pairs), generator=generator)[:k].to(pairs.device)
        pairs, overlaps = pairs[pick], overlaps[pick]
    return pairs, overlaps
