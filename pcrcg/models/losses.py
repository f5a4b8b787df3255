"""Predator's training losses: circle loss on descriptors, weighted BCE on overlap and matchability.

Definitions (Predator, CVPR 2021, and its public training code):

* ground-truth correspondences: source point a and target point b with |T a - b| < overlap_radius;
* circle loss on at most ``max_points`` sampled correspondences: for the sampled source and target
  points, positives are pairs closer than ``pos_radius``, negatives farther than ``safe_radius``;
  with feature distances d (descriptors are unit vectors),

      w_p = max(0, d_p - pos_optimal),  w_n = max(0, neg_optimal - d_n)   (no gradient)
      L_row(i) = softplus( logsumexp_p[ s * w_p * (d_p - pos_margin) ]
                         + logsumexp_n[ s * w_n * (neg_margin - d_n) ] ) / s

  averaged over the rows (and, symmetrically, the columns) that have both a positive and a
  negative, then the two averages are averaged (s = ``log_scale``). As in Predator's code, the
  entries outside a row's positive (negative) set enter its logsumexp with a logit of 0;
* overlap loss: class-balanced BCE on "has a correspondence" for every point of both fragments;
  weights w+ = 1 - mean(label), w- = mean(label);
* matchability loss: the same BCE on the overlap points only, label 1 where the point's mutual-feature
  nearest neighbour among the other fragment's overlap points lies within ``matchability_radius``.

Two coarse losses that Predator does not have (weights 0 by default; the cpu profile turns them on,
``conf/profile/cpu.yaml`` says why): they supervise the bottleneck directly, where the overlap attention
decides which coarse points the other fragment also sees, instead of only through the decoder:

* coarse overlap loss: the same class-balanced BCE on the bottleneck's overlap logits, the label of a
  coarse point being the share of its level-0 points (those that the decoder's nearest upsampling gives
  it) that are in the overlap (a soft label; a coarse point without level-0 points is left out);
* coarse circle loss: the circle loss on the bottleneck features (L2-normalised), all source x target
  coarse points, with the radii in voxels of the coarsest level.

All radii are given in metres here; the config gives them in voxel units (see :class:`LossConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from pcrcg.fields import NodeSettings
from pcrcg.models.kpconv.conv import get_implementation


OFFICIAL = "official"
PREDATOR_MATCHABILITY_AFTER_RECALL = 0.3  # Predator's trainer: the matchability loss on after a validation above this


@dataclass
class LossConfig(NodeSettings):
    """Loss settings; ``*_radius`` in units of the model voxel size (Predator at 2.5 cm:
    pos/overlap 0.0375 m = 1.5 voxels, safe 0.1 m = 4, matchability 0.05 m = 2)."""

    pos_radius: float = 1.5
    safe_radius: float = 4.0
    overlap_radius: float = 1.5
    matchability_radius: float = 2.0
    pos_margin: float = 0.1
    neg_margin: float = 1.4
    pos_optimal: float = 0.1
    neg_optimal: float = 1.4
    log_scale: float = 16.0  # what Predator / PCR-CG trained with (their configs' 24 never reaches the loss)
    max_points: int = 256
    w_circle: float = 1.0
    w_overlap: float = 1.0
    w_matchability: float = 1.0
    # when the matchability loss is on: "official" (each run's official trainer, :meth:`matchability_threshold`), or
    # a threshold of the validation feature-match recall for every run (0: always on)
    matchability_after_recall: float | str = OFFICIAL
    # coarse losses on the bottleneck (not Predator's; see the module docstring)
    w_coarse_overlap: float = 0.0
    w_coarse_circle: float = 0.0

    def __post_init__(self) -> None:
        from pcrcg.errors import ConfigError

        for name in ("pos_radius", "safe_radius", "overlap_radius", "matchability_radius", "log_scale"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ConfigError(f"model.loss.{name}", v, "a positive number")
        for name in ("w_circle", "w_overlap", "w_matchability", "w_coarse_overlap", "w_coarse_circle"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
                raise ConfigError(f"model.loss.{name}", v, "a number >= 0")
        v = self.matchability_after_recall
        if v != OFFICIAL and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < 1):
            raise ConfigError("model.loss.matchability_after_recall", v,
                              f"{OFFICIAL} | a validation feature-match recall in [0, 1) (0: always on)")

    def matchability_threshold(self, lifted: bool) -> float:
        """The validation feature-match recall above which the matchability loss is on (0: from the first step).
        ``official``: what each official trainer does. Predator's (geometry only, ``lifted`` False) weights the loss
        by a ``w_saliency_loss`` that it sets to 1 after a validation whose recall is above 0.3 and to 0 otherwise
        (prs-eth/OverlapPredator, lib/trainer.py); PCR-CG's (2D features lifted) sets the same weight but sums
        the losses without it (Gardlin/PCR-CG, lib/trainer.py: ``c_loss += res[k]`` for the circle, overlap and
        saliency losses), so its matchability loss is on from the first step."""
        v = self.matchability_after_recall
        if v == OFFICIAL:
            return 0.0 if lifted else PREDATOR_MATCHABILITY_AFTER_RECALL
        return float(v)


def circle_loss(coords_dist: torch.Tensor, feats_dist: torch.Tensor, pos_radius: float, safe_radius: float,
                pos_margin: float = 0.1, neg_margin: float = 1.4, pos_optimal: float = 0.1,
                neg_optimal: float = 1.4, log_scale: float = 16.0) -> torch.Tensor:
    """Circle loss of a source x target block: coords_dist, feats_dist (n, m) -> scalar.

    Returns 0 (connected to the graph) when no row or column has both a positive and a negative.
    """
    return masked_circle_loss(coords_dist < pos_radius, coords_dist > safe_radius, feats_dist, pos_margin,
                              neg_margin, pos_optimal, neg_optimal, log_scale)


def masked_circle_loss(pos: torch.Tensor, neg: torch.Tensor, feats_dist: torch.Tensor, pos_margin: float = 0.1,
                       neg_margin: float = 1.4, pos_optimal: float = 0.1, neg_optimal: float = 1.4,
                       log_scale: float = 16.0, pos_scales: torch.Tensor | None = None) -> torch.Tensor:
    """The circle loss given the positive and negative masks (n, m) bool; ``pos_scales`` (n, m)
    multiplies the positives' weights (GeoTransformer's overlap-aware variant: sqrt of the overlap).

    Computed by :func:`_circle_logsumexps` (the four log-sum-exps in one autograd node, the positives
    as a sparse set); the KPConv implementation ``dense`` (:func:`pcrcg.models.kpconv.implementation`,
    the previous code) runs the reference, :func:`masked_circle_loss_reference`. The two agree to float
    rounding (``tests/test_speed_equivalence.py``)."""
    if get_implementation() == "dense":
        return masked_circle_loss_reference(pos, neg, feats_dist, pos_margin, neg_margin, pos_optimal, neg_optimal,
                                            log_scale, pos_scales)
    row_sel = _any(pos, -1) & _any(neg, -1)
    col_sel = _any(pos, -2) & _any(neg, -2)
    lse_pos_row, lse_neg_row, lse_pos_col, lse_neg_col = _CircleLogSumExps.apply(
        feats_dist, pos, neg, pos_margin, neg_margin, pos_optimal, neg_optimal, log_scale,
        None if pos_scales is None else pos_scales.detach())
    loss_row = F.softplus(lse_pos_row + lse_neg_row) / log_scale
    loss_col = F.softplus(lse_pos_col + lse_neg_col) / log_scale
    return _mean_of_sides(loss_row, row_sel, loss_col, col_sel, feats_dist)


def _mean_of_sides(loss_row: torch.Tensor, row_sel: torch.Tensor, loss_col: torch.Tensor, col_sel: torch.Tensor,
                   feats_dist: torch.Tensor) -> torch.Tensor:
    """Mean of the selected rows' and the selected columns' losses, averaged (Predator); with one side
    empty the other; with both empty a zero that keeps the graph of ``feats_dist``."""
    parts = []
    if row_sel.any():
        parts.append(loss_row[row_sel].mean())
    if col_sel.any():
        parts.append(loss_col[col_sel].mean())
    if not parts:
        return feats_dist.sum() * 0.0
    return torch.stack(parts).mean()


def _any(mask: torch.Tensor, dim: int) -> torch.Tensor:
    """``mask.sum(dim) > 0`` of a bool tensor, as the max of its bytes (the sum converts the mask to int64
    and ``any`` reduces slowly on the CPU: 2 ms against 0.05 ms for 1024 x 1024)."""
    return mask.view(torch.uint8).amax(dim) > 0


class _CircleLogSumExps(torch.autograd.Function):
    """The circle loss's log-sum-exps over the rows and the columns of its positive and negative logits,
    feats_dist (n, m) -> (pos rows (n,), neg rows (n,), pos columns (m,), neg columns (m,)), with the
    reference's logits (:func:`masked_circle_loss_reference`, the same operations bit for bit):

    * positive logits are 0 outside the positive mask (a weight of exactly 0 there), so they are kept
      only on the (few) positives, and each row's / column's zeros enter its sum as a count;
    * negative logits are dense; their log-sum-exps are torch's formula (max, exp of the differences, sum,
      log + max: the same values bit for bit), and the backward reuses the exponentials of the forward
      (softmax = exp / sum instead of exp(x - lse): float rounding only).

    The gradient goes to ``feats_dist`` only (the weights are constants, as the reference's detach)."""

    @staticmethod
    def forward(ctx, fd, pos, neg, pos_margin, neg_margin, pos_optimal, neg_optimal,  # type: ignore[override]
                log_scale, pos_scales):
        n, m = fd.shape
        # negatives (dense): w = max(0, neg_optimal - d) on the mask, 0 elsewhere; logit s * (margin - d) * w
        w_neg = torch.clamp(neg_optimal - fd, min=0).masked_fill_(~neg, 0.0)
        x_neg = (neg_margin - fd).mul_(log_scale).mul_(w_neg)
        lse, expd, sums = [], [], []
        for dim in (1, 0):
            mx = x_neg.amax(dim, keepdim=True)
            mx.masked_fill_(mx.abs() == float("inf"), 0.0)
            e = (x_neg - mx).exp_()
            s = e.sum(dim)
            lse.append(s.log().add_(mx.squeeze(dim)))
            expd.append(e)
            sums.append(s)
        del x_neg
        # positives (sparse): logit s * (d - margin) * w, w = max(0, d - pos_optimal) (* scale)
        ii, jj = pos.nonzero(as_tuple=True)
        fd_p = fd[ii, jj]
        w_pos = torch.clamp(fd_p - pos_optimal, min=0)
        if pos_scales is not None:
            w_pos = w_pos * pos_scales[ii, jj]
        x_pos = log_scale * (fd_p - pos_margin) * w_pos
        lse_pos = []
        for idx, size, other in ((ii, n, m), (jj, m, n)):
            zeros = other - torch.bincount(idx, minlength=size).to(fd.dtype)  # entries whose logit is 0
            mx = fd.new_full((size,), float("-inf")).scatter_reduce_(0, idx, x_pos, "amax")
            mx = torch.where(zeros > 0, mx.clamp(min=0), mx)
            mx.masked_fill_(mx.abs() == float("inf"), 0.0)
            s = (zeros * torch.exp(-mx)).index_add_(0, idx, torch.exp(x_pos - mx[idx]))
            lse_pos.append(s.log().add_(mx))
        ctx.save_for_backward(w_neg, expd[0], expd[1], sums[0], sums[1], ii, jj, w_pos, x_pos, lse_pos[0], lse_pos[1])
        ctx.log_scale = log_scale
        return lse_pos[0], lse[0], lse_pos[1], lse[1]

    @staticmethod
    def backward(ctx, g_pos_row, g_neg_row, g_pos_col, g_neg_col):  # type: ignore[override]
        w_neg, e_row, e_col, s_row, s_col, ii, jj, w_pos, x_pos, lse_pr, lse_pc = ctx.saved_tensors
        s = ctx.log_scale
        n, m = w_neg.shape
        z_n, z_m = w_neg.new_zeros(n), w_neg.new_zeros(m)
        g_pos_row = z_n if g_pos_row is None else g_pos_row
        g_neg_row = z_n if g_neg_row is None else g_neg_row
        g_pos_col = z_m if g_pos_col is None else g_pos_col
        g_neg_col = z_m if g_neg_col is None else g_neg_col
        # d logit_neg / d d = -s * w_neg; d lse / d logit = softmax
        grad = e_row.mul_((g_neg_row / s_row).unsqueeze(1))
        grad.add_(e_col.mul_((g_neg_col / s_col).unsqueeze(0)))
        grad.mul_(w_neg).mul_(-s)
        g_p = g_pos_row[ii] * torch.exp(x_pos - lse_pr[ii]) + g_pos_col[jj] * torch.exp(x_pos - lse_pc[jj])
        grad.index_put_((ii, jj), (s * w_pos) * g_p, accumulate=True)
        return grad, None, None, None, None, None, None, None, None


def masked_circle_loss_reference(pos: torch.Tensor, neg: torch.Tensor, feats_dist: torch.Tensor,
                                 pos_margin: float = 0.1, neg_margin: float = 1.4, pos_optimal: float = 0.1,
                                 neg_optimal: float = 1.4, log_scale: float = 16.0,
                                 pos_scales: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`masked_circle_loss` in plain autograd operations (the previous code; dense (n, m) logits)."""
    row_sel = (pos.sum(-1) > 0) & (neg.sum(-1) > 0)
    col_sel = (pos.sum(-2) > 0) & (neg.sum(-2) > 0)
    big = 1e5
    w_pos = torch.clamp(feats_dist - big * (~pos).float() - pos_optimal, min=0).detach()
    if pos_scales is not None:
        w_pos = w_pos * pos_scales.detach()
    w_neg = torch.clamp(neg_optimal - (feats_dist + big * (~neg).float()), min=0).detach()
    pos_term = log_scale * (feats_dist - pos_margin) * w_pos
    neg_term = log_scale * (neg_margin - feats_dist) * w_neg
    loss_row = F.softplus(torch.logsumexp(pos_term, -1) + torch.logsumexp(neg_term, -1)) / log_scale
    loss_col = F.softplus(torch.logsumexp(pos_term, -2) + torch.logsumexp(neg_term, -2)) / log_scale
    return _mean_of_sides(loss_row, row_sel, loss_col, col_sel, feats_dist)


def weighted_bce(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Class-balanced BCE: logits (N,), labels (N,) in {0, 1} -> scalar (Predator's weights)."""
    if labels.numel() == 0:
        return logits.sum() * 0.0
    labels = labels.to(logits.dtype)
    w_neg = labels.mean()
    w_pos = 1.0 - w_neg
    weights = torch.where(labels >= 0.5, w_pos, w_neg).detach()
    return (weights * F.binary_cross_entropy_with_logits(logits, labels, reduction="none")).mean()


def precision_recall(prob: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Binary precision and recall at 0.5 (0 where undefined): prob, labels (N,) -> (p, r)."""
    pred = prob > 0.5
    gt = labels > 0.5
    tp = (pred & gt).sum().float()
    p = tp / pred.sum().clamp(min=1).float()
    r = tp / gt.sum().clamp(min=1).float()
    return p, r


def descriptor_hit_rate(coords_dist: torch.Tensor, feats_dist: torch.Tensor, pos_radius: float,
                        pos: torch.Tensor | None = None) -> torch.Tensor:
    """Fraction of rows with a true positive whose feature nearest neighbour is a positive (a training
    statistic over the sampled rows, logged as ``recall``; not the protocol's feature-match recall,
    :func:`pcrcg.evaluation.metrics.feature_match_recall`). ``pos``: ``coords_dist < pos_radius`` when
    the caller has it already."""
    has_pos = (coords_dist < pos_radius).any(-1) if pos is None else _any(pos, -1)
    nn_idx = feats_dist.argmin(-1, keepdim=True)
    hit = torch.gather(coords_dist, -1, nn_idx).squeeze(-1) < pos_radius
    return (hit & has_pos).sum().float() / has_pos.sum().clamp(min=1).float()


def overlap_labels(n_src: int, n_tgt: int, corr: torch.Tensor, device: torch.device) -> torch.Tensor:
    """1 for points with a correspondence: corr (C, 2) local indices -> (n_src + n_tgt,) float."""
    lab = torch.zeros(n_src + n_tgt, device=device)
    if corr.numel():
        lab[corr[:, 0]] = 1.0
        lab[n_src + corr[:, 1]] = 1.0
    return lab


@torch.no_grad()
def matchability_labels(src_xyz: torch.Tensor, tgt_xyz: torch.Tensor, src_desc: torch.Tensor,
                        tgt_desc: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Whether each point's best descriptor match in the other set is within ``radius``.

    src_xyz (n, 3) already in the target frame, tgt_xyz (m, 3), descriptors (n, D)/(m, D)
    -> labels (n,), (m,) float.
    """
    if len(src_xyz) == 0 or len(tgt_xyz) == 0:
        z = src_xyz.new_zeros
        return z(len(src_xyz)), z(len(tgt_xyz))
    if get_implementation() == "dense" or src_desc.device.type != "cpu":  # the previous code
        scores = src_desc @ tgt_desc.t()
        best_t, best_s = scores.argmax(1), scores.argmax(0)
    else:
        best_t, best_s = _best_scores(src_desc, tgt_desc), _best_scores(tgt_desc, src_desc)
    d1 = torch.linalg.vector_norm(src_xyz - tgt_xyz[best_t], dim=1)
    d2 = torch.linalg.vector_norm(tgt_xyz - src_xyz[best_s], dim=1)
    return (d1 < radius).float(), (d2 < radius).float()


def _best_scores(a: torch.Tensor, b: torch.Tensor, chunk: int = 512) -> torch.Tensor:
    """``(a @ b.t()).argmax(1)`` by blocks of ``chunk`` rows: the (n, m) scores never exist at once (at
    5.8k x 5.7k overlap points: 130 MB), and ``argmax(0)`` of the matrix, a slow strided reduction on the
    CPU (~330 ms there), becomes this row-wise arg-max of ``b @ a.t()`` (whose entries are the same
    products, bit for bit on the CPU BLAS: ``tests/test_speed_equivalence.py``); each block's arg-max by
    :func:`pcrcg.device.argmax_rows` (NumPy's loop on the CPU: the whole call at 5.8k x 5.7k 79 -> 39 ms)."""
    from pcrcg.device import argmax_rows

    bt = b.t()
    return torch.cat([argmax_rows(a[s:s + chunk] @ bt) for s in range(0, a.shape[0], chunk)])


@dataclass
class CoarseInputs:
    """What the coarse losses need of a stacked pair: the bottleneck's overlap ``logits`` (Nc,) and
    ``feats`` (Nc, C), the coarse ``points`` (Nc, 3) (source first, ``n_src`` of them), the coarse point
    of each level-0 point ``assign`` (N0,) long (Nc where there is none) and the coarsest ``voxel`` (m)."""

    logits: torch.Tensor
    feats: torch.Tensor
    points: torch.Tensor
    n_src: int
    assign: torch.Tensor
    voxel: float


def coarse_overlap_labels(fine_labels: torch.Tensor, assign: torch.Tensor, n_coarse: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Share of each coarse point's level-0 points in the overlap: fine_labels (N0,) float, assign (N0,)
    long (``n_coarse`` = none) -> (labels (Nc,) float in [0, 1], has_points (Nc,) bool)."""
    ok = assign < n_coarse
    idx, lab = assign[ok], fine_labels[ok]
    total = torch.zeros(n_coarse, device=fine_labels.device, dtype=lab.dtype).index_add_(0, idx, lab)
    count = torch.zeros(n_coarse, device=fine_labels.device, dtype=lab.dtype).index_add_(0, idx, torch.ones_like(lab))
    return total / count.clamp(min=1), count > 0


def transform_torch(T: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Rigid 4x4 applied to (N, 3) points (torch)."""
    T = T.to(pts.dtype)
    return pts @ T[:3, :3].t() + T[:3, 3]


class PredatorLoss(torch.nn.Module):
    """All of Predator's losses and training statistics for one pair.

    ``forward(descriptors, overlap_logits, matchability_logits, points, n_src, transform, corr,
    w_matchability)`` with level-0 stacked ``points`` (N, 3) (source first), ``transform`` (4, 4)
    mapping source into target, ``corr`` (C, 2) local indices -> dict of scalars
    (``loss``, ``circle_loss``, ``overlap_loss``, ``matchability_loss``, ``recall``,
    ``overlap_precision``, ``overlap_recall``, ``matchability_precision``, ``matchability_recall``,
    ``n_corr``).
    """

    def __init__(self, cfg: LossConfig, voxel_size: float):
        super().__init__()
        self.cfg = cfg
        self.v = float(voxel_size)

    def radius(self, name: str) -> float:
        return getattr(self.cfg, name) * self.v

    def forward(self, descriptors: torch.Tensor, overlap_logits: torch.Tensor, matchability_logits: torch.Tensor,
                points: torch.Tensor, n_src: int, transform: torch.Tensor, corr: torch.Tensor,
                w_matchability: float | torch.Tensor = 1.0,
                generator: torch.Generator | None = None, matchability: bool = True,
                coarse: CoarseInputs | None = None) -> dict[str, torch.Tensor]:
        """``coarse``: the bottleneck's outputs, for the coarse losses (needed when their weights are > 0).
        ``matchability=False`` skips the matchability labels (an (n x m) descriptor product and two
        arg-maxes over the overlap points; a third of a CPU step) while its loss weight is 0."""
        c = self.cfg
        dev = descriptors.device
        src_xyz = transform_torch(transform, points[:n_src])
        tgt_xyz = points[n_src:]
        n_tgt = len(tgt_xyz)
        stats: dict[str, torch.Tensor] = {}

        # overlap: every point, label = has a correspondence
        ov_lab = overlap_labels(n_src, n_tgt, corr, dev)
        stats["overlap_loss"] = weighted_bce(overlap_logits, ov_lab)
        stats["overlap_precision"], stats["overlap_recall"] = precision_recall(torch.sigmoid(overlap_logits), ov_lab)

        # matchability: overlap points only
        if matchability:
            s_idx = torch.unique(corr[:, 0]) if corr.numel() else corr.new_zeros(0)
            t_idx = torch.unique(corr[:, 1]) if corr.numel() else corr.new_zeros(0)
            l_src, l_tgt = matchability_labels(src_xyz[s_idx], tgt_xyz[t_idx], descriptors[s_idx].detach(),
                                               descriptors[n_src + t_idx].detach(), self.radius("matchability_radius"))
            m_lab = torch.cat([l_src, l_tgt])
            m_logit = torch.cat([matchability_logits[s_idx], matchability_logits[n_src + t_idx]])
            stats["matchability_loss"] = weighted_bce(m_logit, m_lab)
            stats["matchability_precision"], stats["matchability_recall"] = precision_recall(
                torch.sigmoid(m_logit), m_lab)
        else:
            stats["matchability_loss"] = matchability_logits.sum() * 0.0

        # circle loss on sampled correspondences closer than pos_radius
        pos_r = self.radius("pos_radius")
        if corr.numel():
            cd = torch.linalg.vector_norm(src_xyz[corr[:, 0]] - tgt_xyz[corr[:, 1]], dim=1)
            corr = corr[cd < pos_r]
        stats["n_corr"] = torch.tensor(float(len(corr)), device=dev)
        if len(corr) > c.max_points:
            pick = torch.randperm(len(corr), generator=generator, device="cpu" if generator is not None else dev)
            corr = corr[pick[: c.max_points].to(corr.device)]
        if len(corr):
            a, b = corr[:, 0], corr[:, 1]
            coords_dist = torch.cdist(src_xyz[a], tgt_xyz[b])
            fd2 = 2.0 - 2.0 * descriptors[a] @ descriptors[n_src + b].t()
            feats_dist = torch.sqrt(torch.clamp(fd2, min=1e-12))
            pos = coords_dist < pos_r  # circle_loss's positives, shared with the hit rate
            stats["circle_loss"] = masked_circle_loss(pos, coords_dist > self.radius("safe_radius"), feats_dist,
                                                      c.pos_margin, c.neg_margin, c.pos_optimal, c.neg_optimal,
                                                      c.log_scale)
            stats["recall"] = descriptor_hit_rate(coords_dist, feats_dist.detach(), pos_r, pos)
        else:
            stats["circle_loss"] = descriptors.sum() * 0.0
            stats["recall"] = torch.tensor(0.0, device=dev)
        stats["loss"] = (c.w_circle * stats["circle_loss"] + c.w_overlap * stats["overlap_loss"]
                         + c.w_matchability * w_matchability * stats["matchability_loss"])
        if c.w_coarse_overlap > 0 or c.w_coarse_circle > 0:
            if coarse is None:
                raise ValueError("the coarse losses are on (model.loss.w_coarse_*) but no coarse outputs were given")
            stats.update(self.coarse_losses(coarse, ov_lab, transform))
            stats["loss"] = (stats["loss"] + c.w_coarse_overlap * stats["coarse_overlap_loss"]
                             + c.w_coarse_circle * stats["coarse_circle_loss"])
        return stats

    def coarse_losses(self, co: CoarseInputs, fine_labels: torch.Tensor, transform: torch.Tensor) -> dict[str, torch.Tensor]:
        """The coarse overlap BCE and coarse circle loss (module docstring) -> dict of scalars
        (``coarse_overlap_loss``, ``coarse_circle_loss``, ``coarse_recall``)."""
        c = self.cfg
        n_c = len(co.points)
        lab, has = coarse_overlap_labels(fine_labels.to(co.logits.dtype), co.assign, n_c)
        out = {"coarse_overlap_loss": weighted_bce(co.logits[has], lab[has])}
        src = transform_torch(transform, co.points[: co.n_src])
        tgt = co.points[co.n_src:]
        coords_dist = torch.cdist(src, tgt)
        fn = F.normalize(co.feats, p=2, dim=1)
        fd2 = 2.0 - 2.0 * fn[: co.n_src] @ fn[co.n_src:].t()
        feats_dist = torch.sqrt(torch.clamp(fd2, min=1e-12))
        pos_r, safe_r = c.pos_radius * co.voxel, c.safe_radius * co.voxel
        out["coarse_circle_loss"] = circle_loss(coords_dist, feats_dist, pos_r, safe_r, c.pos_margin, c.neg_margin,
                                                c.pos_optimal, c.neg_optimal, c.log_scale)
        out["coarse_recall"] = descriptor_hit_rate(coords_dist, feats_dist.detach(), pos_r)
        return out
