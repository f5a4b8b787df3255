"""CoFiNet's losses: the coarse (overlap-aware) and the fine matching loss.

* coarse: ``-sum(M * log A) / sum(M)`` over the coarse log assignment A (Ms + 1, Mt + 1) and the
  overlap-aware soft mask M (:func:`pcrcg.models.cofinet.matching.coarse_targets`, dustbins included);
* fine: the same on each node pair's log assignment with the fine labels
  (:func:`pcrcg.models.cofinet.matching.fine_targets`: true point pairs within ``positive_radius``,
  the unmatched rest of every row and column to the dustbins).
"""

from __future__ import annotations

import torch

from pcrcg.models.cofinet.matching import coarse_targets, fine_targets


def matching_loss(log_assign: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """-sum(labels * log_assign) / sum(labels) (0 with a gradient path when there is no label)."""
    total = labels.sum()
    if not bool(total > 0):
        return log_assign.sum() * 0.0
    return -(labels * log_assign).sum() / total


def cofinet_loss(out, transform: torch.Tensor, corr: torch.Tensor, cfg) -> dict[str, torch.Tensor]:
    """Losses and statistics of one pair from a :class:`~pcrcg.models.cofinet.model.CoFiOutput`, the true
    motion (4, 4) source -> target, the level-0 correspondences (C, 2) and the :class:`CoFiNetConfig`:
    ``loss``, ``coarse_matching_loss`` (also ``circle_loss``: the checkpoint's monitor key),
    ``fine_matching_loss``, ``coarse_precision`` (share of the node pairs used that truly overlap),
    ``fine_precision`` (share of the source points with a true match whose best entry is one)."""
    mask = out.coarse_mask
    if mask is None:
        mask = coarse_targets(out.src_nodes, out.tgt_nodes, out.src_points, out.tgt_points, corr)
    coarse = matching_loss(out.coarse_log, mask)
    stats: dict[str, torch.Tensor] = {"coarse_matching_loss": coarse, "circle_loss": coarse}
    dev = coarse.device
    if len(out.node_pairs):
        a, b = out.node_pairs[:, 0], out.node_pairs[:, 1]
        sm, tm = out.src_patches.mask[a], out.tgt_patches.mask[b]
        labels = fine_targets(out.src_patches.points(out.src_points)[a], out.tgt_patches.points(out.tgt_points)[b],
                              sm, tm, transform, cfg.metres(cfg.positive_radius))
        fine = matching_loss(out.log_assign, labels)
        with torch.no_grad():
            stats["coarse_precision"] = (mask[a, b] > 0).float().mean()
            k = sm.shape[1]
            best = out.log_assign[:, :k, :].argmax(2)  # each source point's best entry (dustbin: k)
            true = labels[:, :k, :] > 0
            hit = torch.gather(true, 2, best.unsqueeze(2)).squeeze(2) & sm
            has = true[:, :, :k].any(2)
            stats["fine_precision"] = (hit & has).sum().float() / has.sum().clamp(min=1).float()
    else:
        fine = out.log_assign.sum() * 0.0 if out.log_assign.numel() else coarse * 0.0
        stats["coarse_precision"] = torch.tensor(0.0, device=dev)
        stats["fine_precision"] = torch.tensor(0.0, device=dev)
    stats["fine_matching_loss"] = fine
    stats["n_node_pairs"] = torch.tensor(float(len(out.node_pairs)), device=dev)
    stats["loss"] = cfg.loss.w_coarse * coarse + cfg.loss.w_fine * fine
    return stats
