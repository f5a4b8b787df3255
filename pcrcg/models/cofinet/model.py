"""CoFiNet (Yu et al., NeurIPS 2021) on the project's KPConv, for a stacked pair (source first).

1. encoder: the shared KPConv encoder (:mod:`pcrcg.models.encoder`), then a linear bottleneck to
   ``gnn_dim`` at the coarsest level (the nodes);
2. coarse: the attention block (self, cross, self: :class:`AttentionStack`) and a linear projection,
   scores ``<f_i, g_j> / sqrt(gnn_dim)`` through the differentiable matching layer (Sinkhorn with a
   learned dustbin score: :class:`pcrcg.models.geotransformer.transport.LearnableOptimalTransport`)
   -> the coarse log assignment (Ms + 1, Mt + 1);
3. decoder: from the attended node features up to level 0 (nearest upsampling, skip concatenation,
   unary blocks halving the width; ``final_dim`` at level 0);
4. node patches: every level-0 point to its nearest node, ``patch_points`` per patch (padded: the
   patches follow the local density, CoFiNet's density-adaptive matching);
5. node pairs: ``num_targets`` ground-truth pairs in training (drawn from the overlap-aware mask),
   the coarse matching's most probable pairs otherwise;
6. fine: in each node pair, local attention (self, cross, self) on the patches' fine features, a linear
   projection, scores / sqrt(final_dim) through Sinkhorn with a dustbin (score 0, as CoFiNet's fine
   matching; padding masked) -> (P, K + 1, K + 1);
7. :meth:`CoFiNet.correspondences`: point pairs and confidences for RANSAC.

The input width ``in_dim`` is the only thing the projection module changes (1 + lifted width).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import torch
from torch import nn
from torch.profiler import record_function

from pcrcg.models.cofinet.attention import AttentionStack
from pcrcg.models.cofinet.config import CoFiNetConfig
from pcrcg.models.cofinet.matching import (
    coarse_targets,
    fine_correspondences,
    sample_targets,
    select_node_pairs,
)
from pcrcg.models.encoder import kpconv_encoder, run_encoder
from pcrcg.models.geotransformer.superpoints import Patches, point_to_node_partition
from pcrcg.models.geotransformer.transport import LearnableOptimalTransport, log_optimal_transport
from pcrcg.models.kpconv.blocks import LastUnaryBlock, NearestUpsampleBlock, UnaryBlock
from pcrcg.models.kpconv.pyramid import TensorPyramid


@dataclass
class CoFiOutput:
    """One pair's outputs (every point in the frames of the batch).

    src_points / tgt_points (Ns, 3) / (Nt, 3): level-0 points; src_feats_f / tgt_feats_f: their fine
    features (decoder output, before the local attention); src_nodes / tgt_nodes (Ms, 3) / (Mt, 3);
    coarse_log (Ms + 1, Mt + 1): the coarse log assignment; src_patches / tgt_patches; node_pairs (P, 2)
    long and node_scores (P,): the node pairs matched in the patches (ground truth in training: their
    mask values); log_assign (P, K + 1, K + 1); coarse_mask (Ms + 1, Mt + 1): the coarse ground truth
    when the correspondences were given.
    """

    src_points: torch.Tensor
    tgt_points: torch.Tensor
    src_feats_f: torch.Tensor
    tgt_feats_f: torch.Tensor
    src_nodes: torch.Tensor
    tgt_nodes: torch.Tensor
    coarse_log: torch.Tensor
    src_patches: Patches
    tgt_patches: Patches
    node_pairs: torch.Tensor
    node_scores: torch.Tensor
    log_assign: torch.Tensor
    coarse_mask: torch.Tensor | None = None


class CoFiNet(nn.Module):
    """``forward(feats, pyr, corr=None, targets=False) -> CoFiOutput``: ``corr`` (C, 2) the level-0
    correspondences (local source, target indices) give the coarse ground truth; ``targets=True``
    (training) matches ground-truth node pairs instead of the predicted ones."""

    def __init__(self, cfg: CoFiNetConfig):
        super().__init__()
        cfg.validate()
        self.cfg = c = cfg
        L = c.num_layers
        self.encoder, self.layout = kpconv_encoder(c.in_dim, c.first_dim, L, c.voxel_size, c.conv_radius,
                                                   c.kp_extent, c.num_kernel_points, c.kernel_seed)
        dims = self.layout.dims
        self.bottleneck = nn.Linear(dims[-1], c.gnn_dim)
        self.attention = AttentionStack(c.gnn_dim, c.num_heads, c.blocks)
        self.coarse_proj = nn.Linear(c.gnn_dim, c.gnn_dim)
        self.coarse_transport = LearnableOptimalTransport(c.sinkhorn_iterations)
        ups, units = [], []
        width = out = c.gnn_dim
        for level in range(L - 2, -1, -1):  # upsample to `level`, concatenate its skip
            ups.append(NearestUpsampleBlock(level + 1))
            if level == 0:
                units.append(LastUnaryBlock(width + dims[level], c.final_dim))
            else:
                out //= 2
                units.append(UnaryBlock(width + dims[level], out))
                width = out
        self.ups, self.units = nn.ModuleList(ups), nn.ModuleList(units)
        self.local_attention = AttentionStack(c.final_dim, c.num_heads, c.local_blocks) if c.local_attention else None
        self.fine_proj = nn.Linear(c.final_dim, c.final_dim)
        self.register_buffer("fine_dustbin", torch.tensor(0.0), persistent=False)

    # ------------------------------------------------------------------ parts
    def coarse_matching(self, src: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
        """Projected node features (Ms, C) / (Mt, C) -> coarse log assignment (Ms + 1, Mt + 1)."""
        scores = (src @ tgt.t() / src.shape[1] ** 0.5).unsqueeze(0)
        ones = lambda n: torch.ones((1, n), dtype=torch.bool, device=src.device)  # noqa: E731
        return self.coarse_transport(scores, ones(src.shape[0]), ones(tgt.shape[0]))[0]

    def fine_matching(self, fs: torch.Tensor, ft: torch.Tensor, sm: torch.Tensor, tm: torch.Tensor) -> torch.Tensor:
        """Patch features (P, K, D) / (P, K, D), masks (P, K) -> log assignment (P, K + 1, K + 1)."""
        if self.local_attention is not None:
            fs, ft = self.local_attention(fs, ft, sm, tm)
        fs, ft = self.fine_proj(fs), self.fine_proj(ft)
        scores = fs @ ft.transpose(1, 2) / fs.shape[2] ** 0.5
        return log_optimal_transport(scores, self.fine_dustbin.to(scores.dtype), sm, tm, self.cfg.sinkhorn_iterations)

    def forward(self, feats: torch.Tensor, pyr: TensorPyramid, corr: torch.Tensor | None = None,
                targets: bool = False) -> CoFiOutput:
        c = self.cfg
        if feats.shape[1] != c.in_dim:
            raise ValueError(f"features have {feats.shape[1]} channels, the model expects in_dim={c.in_dim}")
        with record_function("pcrcg.encoder (KPConv)"):
            coarse, skips = run_encoder(self.encoder, self.layout, feats, pyr)
        msc, _ = pyr.split(c.coarse_level)
        ns, _ = pyr.split(0)
        nodes, points = pyr.points[c.coarse_level], pyr.points[0]
        src_nodes, tgt_nodes, src_pts, tgt_pts = nodes[:msc], nodes[msc:], points[:ns], points[ns:]
        with record_function("pcrcg.attention (coarse)"):
            x = self.bottleneck(coarse)
            src_c, tgt_c = self.attention(x[:msc].unsqueeze(0), x[msc:].unsqueeze(0))
            x = self.coarse_proj(torch.cat([src_c[0], tgt_c[0]], 0))
            coarse_log = self.coarse_matching(x[:msc], x[msc:])
        with record_function("pcrcg.decoder"):
            for up, unit in zip(self.ups, self.units):
                x = up(x, pyr)
                x = unit(torch.cat([x, skips[up.layer - 1]], 1), pyr)
        src_f, tgt_f = x[:ns], x[ns:]
        sp = point_to_node_partition(src_pts, src_nodes, c.patch_points)
        tp = point_to_node_partition(tgt_pts, tgt_nodes, c.patch_points)
        mask = coarse_targets(src_nodes, tgt_nodes, src_pts, tgt_pts, corr) if corr is not None else None
        if targets:
            if mask is None:
                raise ValueError("targets=True needs the ground-truth correspondences")
            node_pairs, node_scores = sample_targets(mask, c.num_targets, c.target_overlap)
        else:
            node_pairs, node_scores = select_node_pairs(coarse_log.detach(), sp.node_mask, tp.node_mask,
                                                        c.coarse_threshold, c.min_coarse_correspondences)
        with record_function("pcrcg.fine matching (patches)"):
            a, b = node_pairs[:, 0], node_pairs[:, 1]
            pad = lambda f: torch.cat([f, f.new_zeros((1, f.shape[1]))], 0)  # noqa: E731
            log_assign = self.fine_matching(pad(src_f)[sp.indices[a]], pad(tgt_f)[tp.indices[b]], sp.mask[a],
                                            tp.mask[b])
        return CoFiOutput(src_pts, tgt_pts, src_f, tgt_f, src_nodes, tgt_nodes, coarse_log, sp, tp, node_pairs,
                          node_scores, log_assign, mask)

    # ------------------------------------------------------------------ inference
    @torch.no_grad()
    def correspondences(self, out: CoFiOutput) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Point pairs of the fine matching -> (source xyz (C, 3), target xyz (C, 3), confidence (C,))."""
        a, b = out.node_pairs[:, 0], out.node_pairs[:, 1]
        g, i, j, conf = fine_correspondences(out.log_assign, out.src_patches.mask[a], out.tgt_patches.mask[b],
                                             out.node_scores, self.cfg.mutual)
        src = out.src_patches.points(out.src_points)[a[g], i]
        tgt = out.tgt_patches.points(out.tgt_points)[b[g], j]
        return src, tgt, conf

    @torch.no_grad()
    def point_scores(self, out: CoFiOutput) -> tuple[torch.Tensor, torch.Tensor]:
        """Per level-0 point of each fragment, its node's best matching probability among the node pairs
        used, divided by the largest (a floor of 1e-3)."""

        def per_point(patches: Patches, n: int, nodes: torch.Tensor) -> torch.Tensor:
            score = torch.zeros(patches.indices.shape[0], device=out.node_scores.device)
            if len(nodes):
                score.scatter_reduce_(0, nodes, out.node_scores.float(), reduce="amax")
            score = score / score.max().clamp(min=1e-12)
            owner = torch.full((n + 1,), -1, dtype=torch.long, device=score.device)
            ids = torch.arange(patches.indices.shape[0], device=score.device).unsqueeze(1).expand_as(patches.indices)
            owner[patches.indices[patches.mask]] = ids[patches.mask]
            own = owner[:n]
            return torch.where(own >= 0, score[own.clamp(min=0)], torch.zeros((), device=score.device)).clamp(min=1e-3)

        return (per_point(out.src_patches, out.src_points.shape[0], out.node_pairs[:, 0]),
                per_point(out.tgt_patches, out.tgt_points.shape[0], out.node_pairs[:, 1]))


def build_cofinet(cfg: Mapping[str, Any] | CoFiNetConfig, in_dim: int | None = None) -> CoFiNet:
    """CoFiNet from the ``model`` config node (``conf/model/cofinet.yaml``)."""
    return CoFiNet(CoFiNetConfig.from_config(cfg, in_dim))
