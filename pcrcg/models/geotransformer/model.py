"""GeoTransformer (Qin et al., CVPR 2022) on the project's KPConv, for a stacked pair (source first).

1. KPConv-FPN backbone: the shared encoder (:mod:`pcrcg.models.encoder`), then a decoder from the
   coarsest level up to level 1 (nearest upsampling, skip concatenation, unary blocks): coarse
   features at level L-1 (the superpoints), fine features (``output_dim``) at level 1;
2. the geometric transformer on the superpoints of both fragments -> unit coarse features;
3. patches: every level-1 point to its nearest superpoint, ``patch_points`` per patch;
4. superpoint correspondences: ground-truth pairs in training (:func:`sample_targets`), the
   dual-normalised matching otherwise;
5. point matching: in each superpoint pair, the fine features' correlation / sqrt(D) through
   optimal transport with a dustbin -> log assignment (P, K+1, K+1);
6. :meth:`GeoTransformer.register`: point pairs by mutual top-k, local-to-global registration.

The input width ``in_dim`` is the only thing the projection module changes (1 + lifted width).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import nn
from torch.profiler import record_function

from pcrcg.models.encoder import kpconv_encoder, run_encoder
from pcrcg.models.geotransformer.config import GeoTransformerConfig
from pcrcg.models.geotransformer.lgr import LGRResult, local_to_global, patch_correspondences
from pcrcg.models.geotransformer.superpoints import (
    Patches,
    patch_overlaps,
    point_to_node_partition,
    sample_targets,
    superpoint_matching,
)
from pcrcg.models.geotransformer.transformer import GeometricTransformer
from pcrcg.models.geotransformer.transport import LearnableOptimalTransport
from pcrcg.models.kpconv.blocks import LastUnaryBlock, NearestUpsampleBlock, UnaryBlock
from pcrcg.models.kpconv.pyramid import TensorPyramid


@dataclass
class GeoOutput:
    """One pair's outputs (every point in the frames of the batch, source first in the pyramid).

    src_fine / tgt_fine (Ns, 3) / (Nt, 3): level-1 points; src_feats_f / tgt_feats_f (Ns, D) / (Nt, D):
    fine features (not normalised); src_nodes / tgt_nodes (Ms, 3) / (Mt, 3) superpoints;
    src_feats_c / tgt_feats_c (Ms, C) / (Mt, C) unit coarse features; src_patches / tgt_patches;
    node_pairs (P, 2) long, node_scores (P,): the superpoint pairs used; log_assign (P, K+1, K+1);
    gt_pairs (G, 2) / gt_overlaps (G,): ground-truth patch overlaps (when the motion was given).
    """

    src_fine: torch.Tensor
    tgt_fine: torch.Tensor
    src_feats_f: torch.Tensor
    tgt_feats_f: torch.Tensor
    src_nodes: torch.Tensor
    tgt_nodes: torch.Tensor
    src_feats_c: torch.Tensor
    tgt_feats_c: torch.Tensor
    src_patches: Patches
    tgt_patches: Patches
    node_pairs: torch.Tensor
    node_scores: torch.Tensor
    log_assign: torch.Tensor
    gt_pairs: torch.Tensor | None = None
    gt_overlaps: torch.Tensor | None = None


class KPConvFPN(nn.Module):
    """``forward(feats (N0, in_dim), pyr) -> (coarse (N_{L-1}, dims[-1]), fine (N_1, output_dim))``."""

    def __init__(self, cfg: GeoTransformerConfig):
        super().__init__()
        L = cfg.num_layers
        self.encoder, self.layout = kpconv_encoder(cfg.in_dim, cfg.first_dim, L, cfg.voxel_size, cfg.conv_radius,
                                                   cfg.kp_extent, cfg.num_kernel_points, cfg.kernel_seed)
        dims = self.layout.dims
        ups, units = [], []
        width = dims[-1]
        for level in range(L - 2, 0, -1):  # upsample to `level`, concatenate its skip
            ups.append(NearestUpsampleBlock(level + 1))
            if level == 1:
                units.append(LastUnaryBlock(width + dims[level], cfg.output_dim))
            else:
                units.append(UnaryBlock(width + dims[level], dims[level]))
                width = dims[level]
        self.ups, self.units = nn.ModuleList(ups), nn.ModuleList(units)

    def forward(self, feats: torch.Tensor, pyr: TensorPyramid) -> tuple[torch.Tensor, torch.Tensor]:
        coarse, skips = run_encoder(self.encoder, self.layout, feats, pyr)
        x = coarse
        for up, unit in zip(self.ups, self.units):
            x = up(x, pyr)
            x = unit(torch.cat([x, skips[up.layer - 1]], 1), pyr)
        return coarse, x


class GeoTransformer(nn.Module):
    """``forward(feats, pyr, transform=None, targets=False) -> GeoOutput``: ``transform`` (4, 4)
    source -> target gives the ground-truth patch overlaps; ``targets=True`` (training) matches the
    ground-truth superpoint pairs instead of the predicted ones."""

    def __init__(self, cfg: GeoTransformerConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.backbone = KPConvFPN(cfg)
        self.transformer = GeometricTransformer(self.backbone.layout.dims[-1], cfg.hidden_dim, cfg.hidden_dim,
                                                cfg.num_heads, cfg.blocks, cfg.metres(cfg.sigma_d), cfg.sigma_a,
                                                cfg.angle_k)
        if cfg.embedding_memo_mb is not None:
            self.transformer.embedding.memo_bytes = int(cfg.embedding_memo_mb * 2**20)
        self.transport = LearnableOptimalTransport(cfg.sinkhorn_iterations)

    def forward(self, feats: torch.Tensor, pyr: TensorPyramid, transform: torch.Tensor | None = None,
                targets: bool = False) -> GeoOutput:
        c = self.cfg
        if feats.shape[1] != c.in_dim:
            raise ValueError(f"features have {feats.shape[1]} channels, the model expects in_dim={c.in_dim}")
        with record_function("pcrcg.encoder (KPConv)"):
            coarse, fine = self.backbone(feats, pyr)
        nsc, _ = pyr.split(c.coarse_level)
        nsf, _ = pyr.split(c.fine_level)
        nodes, points = pyr.points[c.coarse_level], pyr.points[c.fine_level]
        src_nodes, tgt_nodes, src_fine, tgt_fine = nodes[:nsc], nodes[nsc:], points[:nsf], points[nsf:]
        with record_function("pcrcg.attention (geometric transformer)"):
            src_c, tgt_c = self.transformer(src_nodes, tgt_nodes, coarse[:nsc], coarse[nsc:])
            src_c, tgt_c = F.normalize(src_c, dim=1), F.normalize(tgt_c, dim=1)
        sp = point_to_node_partition(src_fine, src_nodes, c.patch_points)
        tp = point_to_node_partition(tgt_fine, tgt_nodes, c.patch_points)
        gt_pairs = gt_overlaps = None
        if transform is not None:
            gt_pairs, gt_overlaps = patch_overlaps(src_nodes, tgt_nodes, src_fine, tgt_fine, sp, tp, transform,
                                                   c.metres(c.matching_radius))
        if targets:
            if gt_pairs is None:
                raise ValueError("targets=True needs the true transform")
            node_pairs, node_scores = sample_targets(gt_pairs, gt_overlaps, c.num_targets, c.target_overlap)
        else:
            node_pairs, node_scores = superpoint_matching(src_c.detach(), tgt_c.detach(), sp.node_mask, tp.node_mask,
                                                          c.num_correspondences, c.dual_normalization)
        with record_function("pcrcg.point matching (optimal transport)"):
            src_f, tgt_f = fine[:nsf], fine[nsf:]
            a, b = node_pairs[:, 0], node_pairs[:, 1]
            pad = lambda x: torch.cat([x, x.new_zeros((1, x.shape[1]))], 0)  # noqa: E731
            fs, ft = pad(src_f)[sp.indices[a]], pad(tgt_f)[tp.indices[b]]  # (P, K, D)
            scores = fs @ ft.transpose(1, 2) / fine.shape[1] ** 0.5
            log_assign = self.transport(scores, sp.mask[a], tp.mask[b])
        return GeoOutput(src_fine, tgt_fine, src_f, tgt_f, src_nodes, tgt_nodes, src_c, tgt_c, sp, tp, node_pairs,
                         node_scores, log_assign, gt_pairs, gt_overlaps)

    @torch.no_grad()
    def register(self, out: GeoOutput) -> LGRResult:
        """Point pairs from the assignments (mutual top-k above the confidence threshold) and LGR."""
        c = self.cfg
        a, b = out.node_pairs[:, 0], out.node_pairs[:, 1]
        sm, tm = out.src_patches.mask[a], out.tgt_patches.mask[b]
        chosen, s = patch_correspondences(out.log_assign, sm, tm, c.topk, c.confidence_threshold, c.mutual)
        g, i, j = chosen.nonzero(as_tuple=True)
        src = out.src_patches.points(out.src_fine)[a][g, i]
        tgt = out.tgt_patches.points(out.tgt_fine)[b][g, j]
        return local_to_global(src, tgt, s[g, i, j], g, c.metres(c.acceptance_radius), c.correspondence_threshold,
                               c.refinement_steps)

    @torch.no_grad()
    def point_scores(self, out: GeoOutput) -> tuple[torch.Tensor, torch.Tensor]:
        """Per fine point of each fragment, the best score of its superpoint among the superpoint pairs
        used, divided by the largest (in [0, 1]; a floor of 1e-3): the evaluation samples by it."""
        dev = out.src_fine.device

        def per_point(patches: Patches, n_points: int, nodes: torch.Tensor) -> torch.Tensor:
            node_score = torch.zeros(patches.indices.shape[0], device=dev)
            if len(nodes):
                node_score.scatter_reduce_(0, nodes, out.node_scores.float(), reduce="amax")
            top = node_score.max().clamp(min=1e-12)
            owner = torch.full((n_points + 1,), -1, dtype=torch.long, device=dev)
            ids = torch.arange(patches.indices.shape[0], device=dev).unsqueeze(1).expand_as(patches.indices)
            owner[patches.indices[patches.mask]] = ids[patches.mask]
            score = torch.where(owner[:n_points] >= 0, node_score[owner[:n_points].clamp(min=0)] / top,
                                torch.zeros((), device=dev))
            return score.clamp(min=1e-3)

        return (per_point(out.src_patches, out.src_fine.shape[0], out.node_pairs[:, 0]),
                per_point(out.tgt_patches, out.tgt_fine.shape[0], out.node_pairs[:, 1]))


def build_geotransformer(cfg: Mapping[str, Any] | GeoTransformerConfig, in_dim: int | None = None) -> GeoTransformer:
    """GeoTransformer from the ``model`` config node (``conf/model/geotransformer.yaml``)."""
    return GeoTransformer(GeoTransformerConfig.from_config(cfg, in_dim))
