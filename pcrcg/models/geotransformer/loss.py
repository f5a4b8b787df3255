"""GeoTransformer's losses: the overlap-aware circle loss on superpoints and the point-matching loss.

* coarse: the circle loss (:func:`pcrcg.models.losses.masked_circle_loss`) between every source and
  target superpoint, positives where the patches overlap by more than ``positive_overlap`` (weighted
  by the square root of the overlap), negatives where they do not overlap at all;
* fine: for each superpoint pair used for point matching, the negative log assignment of the true
  point pairs (closer than ``positive_radius`` after the true motion), of the unmatched source points
  to the target's dustbin and of the unmatched target points to the source's.
"""

from __future__ import annotations

import torch

from pcrcg.models.geotransformer.config import GeoLossConfig
from pcrcg.models.geotransformer.superpoints import dense_overlaps, transform_points
from pcrcg.models.losses import masked_circle_loss


def overlap_aware_circle_loss(src_feats: torch.Tensor, tgt_feats: torch.Tensor, overlaps: torch.Tensor,
                              cfg: GeoLossConfig) -> torch.Tensor:
    """Unit features (Ms, C) / (Mt, C), overlaps (Ms, Mt) -> scalar."""
    fd = torch.sqrt(torch.clamp(2.0 - 2.0 * src_feats @ tgt_feats.t(), min=1e-12))
    pos = overlaps > cfg.positive_overlap
    neg = overlaps == 0
    return masked_circle_loss(pos, neg, fd, cfg.positive_margin, cfg.negative_margin, cfg.positive_optimal,
                              cfg.negative_optimal, cfg.log_scale, pos_scales=torch.sqrt(overlaps * pos))


@torch.no_grad()
def point_matching_labels(src_pts: torch.Tensor, tgt_pts: torch.Tensor, src_mask: torch.Tensor,
                          tgt_mask: torch.Tensor, transform: torch.Tensor, radius: float) -> torch.Tensor:
    """Patch points (B, K, 3) each in its own frame, masks (B, K), transform (4, 4) -> labels
    (B, K+1, K+1) bool: true pairs, unmatched source rows -> last column, unmatched target columns -> last row."""
    b, k, _ = src_pts.shape
    d = torch.cdist(transform_points(transform, src_pts), tgt_pts)
    match = (d < radius) & src_mask.unsqueeze(2) & tgt_mask.unsqueeze(1)
    labels = torch.zeros((b, k + 1, k + 1), dtype=torch.bool, device=src_pts.device)
    labels[:, :k, :k] = match
    labels[:, :k, k] = (~match.any(2)) & src_mask
    labels[:, k, :k] = (~match.any(1)) & tgt_mask
    return labels


def point_matching_loss(log_assign: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """log_assign, labels (B, K+1, K+1) -> mean negative log assignment of the labelled entries."""
    if not bool(labels.any()):
        return log_assign.sum() * 0.0
    return -log_assign[labels].mean()


def geotransformer_loss(out, transform: torch.Tensor, cfg: GeoLossConfig, voxel: float) -> dict[str, torch.Tensor]:
    """All losses and statistics of one pair from a :class:`~pcrcg.models.geotransformer.model.GeoOutput`
    and the true motion (4, 4) source -> target: ``loss``, ``circle_loss`` (coarse),
    ``point_matching_loss``, ``superpoint_precision`` (share of the superpoint pairs used that truly
    overlap), ``point_precision`` (share of the predicted point pairs within ``positive_radius``),
    ``n_superpoint_pairs``."""
    ms, mt = out.src_feats_c.shape[0], out.tgt_feats_c.shape[0]
    overlaps = dense_overlaps(out.gt_pairs, out.gt_overlaps, ms, mt)
    coarse = overlap_aware_circle_loss(out.src_feats_c, out.tgt_feats_c, overlaps, cfg)
    radius = float(cfg.positive_radius) * float(voxel)
    stats: dict[str, torch.Tensor] = {"circle_loss": coarse}
    dev = coarse.device
    if len(out.node_pairs):
        a, b = out.node_pairs[:, 0], out.node_pairs[:, 1]
        sp, tp = out.src_patches.points(out.src_fine)[a], out.tgt_patches.points(out.tgt_fine)[b]
        sm, tm = out.src_patches.mask[a], out.tgt_patches.mask[b]
        labels = point_matching_labels(sp, tp, sm, tm, transform, radius)
        fine = point_matching_loss(out.log_assign, labels)
        with torch.no_grad():
            stats["superpoint_precision"] = (overlaps[a, b] > 0).float().mean()
            k = sm.shape[1]
            pred = torch.exp(out.log_assign[:, :k, :k]).argmax(2)  # each source point's best target point
            hit = torch.gather(labels[:, :k, :k], 2, pred.unsqueeze(2)).squeeze(2) & sm
            has = labels[:, :k, :k].any(2)
            stats["point_precision"] = hit.sum().float() / has.sum().clamp(min=1).float()
    else:
        fine = out.log_assign.sum() * 0.0 if out.log_assign.numel() else coarse * 0.0
        stats["superpoint_precision"] = torch.tensor(0.0, device=dev)
        stats["point_precision"] = torch.tensor(0.0, device=dev)
    stats["point_matching_loss"] = fine
    stats["n_superpoint_pairs"] = torch.tensor(float(len(out.node_pairs)), device=dev)
    stats["loss"] = cfg.w_coarse * coarse + cfg.w_fine * fine
    return stats
