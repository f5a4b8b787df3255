"""CoFiNet's ground truth and correspondence selection, coarse (nodes) and fine (points in patches).

* :func:`coarse_targets`: the overlap-aware node matching mask (Ms + 1, Mt + 1) from the level-0
  point correspondences: ``c_ij`` true point pairs between the points of node i and node j; each
  node's visible ratio ``v`` = share of its points with a correspondence; the entry is
  ``min(c_ij / sum_j c_ij * v_i, c_ij / sum_i c_ij * v_j)``, the dustbin column ``1 - v_i`` and the
  dustbin row ``1 - v_j`` (CoFiNet's soft weighted mask). Every point belongs to its nearest node.
* :func:`select_node_pairs`: test time, the node pairs whose matching probability exceeds the
  threshold, at least ``minimum`` of them (the most probable; CoFiNet lowers the threshold in steps of
  0.001 until there are enough, which keeps the same pairs up to ties within a step).
* :func:`fine_targets`: per node pair, true point pairs (closer than ``radius`` after the true motion),
  the rest of each row / column to the dustbin (``max(0, 1 - matches)``), padding left out.
* :func:`fine_correspondences`: in each patch pair, every source point's and every target point's best
  entry (dustbins included; union, or their intersection when ``mutual``) among the real points,
  confidence = its probability x the node pair's.
"""

from __future__ import annotations

import torch

from pcrcg.models.geotransformer.superpoints import Patches, transform_points


@torch.no_grad()
def nearest_node(points: torch.Tensor, nodes: torch.Tensor) -> torch.Tensor:
    """(N,) index of each point's nearest node."""
    return torch.cdist(points, nodes).argmin(dim=1)


@torch.no_grad()
def coarse_targets(src_nodes: torch.Tensor, tgt_nodes: torch.Tensor, src_points: torch.Tensor,
                   tgt_points: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
    """Nodes (Ms, 3) / (Mt, 3), level-0 points (Ns, 3) / (Nt, 3), correspondences (C, 2) long (source,
    target indices) -> the soft matching mask (Ms + 1, Mt + 1), float (see the module docstring)."""
    ms, mt = src_nodes.shape[0], tgt_nodes.shape[0]
    so, to = nearest_node(src_points, src_nodes), nearest_node(tgt_points, tgt_nodes)
    dtype = src_points.dtype

    def visible(owner: torch.Tensor, seen: torch.Tensor, m: int) -> torch.Tensor:
        total = torch.bincount(owner, minlength=m).clamp(min=1).to(dtype)
        flag = torch.zeros(owner.shape[0], dtype=torch.bool, device=owner.device)
        flag[seen] = True
        return torch.bincount(owner[flag], minlength=m).to(dtype) / total

    mask = src_points.new_zeros((ms + 1, mt + 1))
    if corr.shape[0] == 0:
        mask[:ms, mt] = 1.0
        mask[ms, :mt] = 1.0
        return mask
    vs, vt = visible(so, corr[:, 0], ms), visible(to, corr[:, 1], mt)
    counts = src_points.new_zeros((ms, mt))
    counts.index_put_((so[corr[:, 0]], to[corr[:, 1]]), torch.ones(corr.shape[0], dtype=dtype, device=counts.device),
                      accumulate=True)
    rows = counts / (counts.sum(1, keepdim=True) + 1e-10) * vs.unsqueeze(1)
    cols = counts / (counts.sum(0, keepdim=True) + 1e-10) * vt.unsqueeze(0)
    mask[:ms, :mt] = torch.minimum(rows, cols)
    mask[:ms, mt] = 1.0 - vs
    mask[ms, :mt] = 1.0 - vt
    return mask


@torch.no_grad()
def sample_targets(mask: torch.Tensor, k: int, threshold: float = 0.0,
                   generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Training node pairs: ``k`` drawn with replacement (as CoFiNet) among the pairs whose mask entry
    exceeds ``threshold`` -> (pairs (k, 2) long, their mask values (k,)); none when no pair overlaps."""
    pairs = (mask[:-1, :-1] > threshold).nonzero()
    if len(pairs) == 0:
        return pairs, mask.new_zeros(0)
    pick = torch.randint(len(pairs), (int(k),), generator=generator, device="cpu").to(pairs.device)
    pairs = pairs[pick]
    return pairs, mask[pairs[:, 0], pairs[:, 1]]


@torch.no_grad()
def select_node_pairs(log_assign: torch.Tensor, src_valid: torch.Tensor, tgt_valid: torch.Tensor, threshold: float,
                      minimum: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Test-time node pairs from the coarse log assignment (Ms + 1, Mt + 1) and the nodes that own
    points (Ms,) / (Mt,) bool -> (pairs (P, 2) long, probabilities (P,))."""
    p = torch.exp(log_assign[:-1, :-1]).masked_fill(~(src_valid.unsqueeze(1) & tgt_valid.unsqueeze(0)), -1.0)
    flat = p.flatten()
    chosen = (flat > threshold).nonzero().squeeze(1)
    if len(chosen) < minimum:
        k = min(int(minimum), int((flat >= 0).sum()))
        chosen = flat.topk(k).indices
    rows, cols = chosen // p.shape[1], chosen % p.shape[1]
    return torch.stack([rows, cols], 1), flat[chosen]


@torch.no_grad()
def fine_targets(src_pts: torch.Tensor, tgt_pts: torch.Tensor, src_mask: torch.Tensor, tgt_mask: torch.Tensor,
                 transform: torch.Tensor, radius: float) -> torch.Tensor:
    """Patch points (P, K, 3) in their frames, masks (P, K) bool, transform (4, 4) source -> target ->
    labels (P, K + 1, K + 1) float (see the module docstring)."""
    p, k, _ = src_pts.shape
    d = torch.cdist(transform_points(transform, src_pts), tgt_pts)
    match = ((d < radius) & src_mask.unsqueeze(2) & tgt_mask.unsqueeze(1)).to(src_pts.dtype)
    labels = src_pts.new_zeros((p, k + 1, k + 1))
    labels[:, :k, :k] = match
    labels[:, :k, k] = (1.0 - match.sum(2)).clamp(min=0) * src_mask
    labels[:, k, :k] = (1.0 - match.sum(1)).clamp(min=0) * tgt_mask
    return labels


@torch.no_grad()
def fine_correspondences(log_assign: torch.Tensor, src_mask: torch.Tensor, tgt_mask: torch.Tensor,
                         node_scores: torch.Tensor, mutual: bool = False
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """log_assign (P, K + 1, K + 1), masks (P, K), node-pair probabilities (P,) -> (pair g, source slot i,
    target slot j, confidence) of every chosen point pair (each (C,))."""
    k = log_assign.shape[1] - 1
    prob = torch.exp(log_assign)
    rows = torch.zeros_like(prob, dtype=torch.bool)
    cols = torch.zeros_like(prob, dtype=torch.bool)
    rows.scatter_(2, prob[:, :k, :].argmax(2, keepdim=True), True)  # each source point's best entry
    cols.scatter_(1, prob[:, :, :k].argmax(1, keepdim=True), True)  # each target point's best entry
    pick = (rows & cols) if mutual else (rows | cols)
    pick = pick[:, :k, :k] & src_mask.unsqueeze(2) & tgt_mask.unsqueeze(1)
    g, i, j = pick.nonzero(as_tuple=True)
    return g, i, j, prob[g, i, j] * node_scores[g].to(prob.dtype)


def patch_points(patches: Patches, points: torch.Tensor, nodes: torch.Tensor) -> torch.Tensor:
    """The patches' points (P, K, 3) of the node indices ``nodes`` (P,), padding at the origin."""
    return patches.points(points)[nodes]
