"""The Lightning module: the 3D network (``model.name``: ``predator`` | ``geotransformer``) + (optionally)
the 2D encoder and the 2D->3D projection module.

``projection=none`` (or ``features=none``): geometry only, the 3D input is a constant 1 per point
(``in_dim = 1``). Otherwise a :class:`pcrcg.lifting.ColorLifter` (which holds the 2D feature
extractor and its encoder as submodules, so the 3D loss trains them end to end) lifts color
features onto the level-0 points of both fragments in their own frames, and the input is
``[1, lifted features]`` (``in_dim = 1 + lifter.out_dim``): the paper's only change to the network.

``encoder2d.training`` says whether the 3D loss trains the 2D branch: ``detached`` (the official
code: the lifted features are detached, the 2D network is never optimised; it runs without
gradients, and its BatchNorm statistics follow the module's train/eval mode as a network left in
train mode does) or ``end_to_end`` (the paper's text). A lifting config without the key (an older
checkpoint) trains end to end, as those did.

Optimisation as the paper / Predator: SGD (lr 0.005, momentum 0.98, weight decay 1e-6), the
learning rate times 0.95 after every epoch, batch size 1. The matchability loss is on as the run's official
trainer has it (``loss.matchability_after_recall: official``): geometry-only, once the validation feature-match
recall exceeds 0.3 (Predator's schedule); with lifted 2D features, from the first step (PCR-CG's trainer).
"""

from __future__ import annotations

import contextlib
import math

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, Mapping, NamedTuple

import lightning as L
import numpy as np
import torch
from torch.profiler import record_function  # stage labels (pcrcg.benchmarks.model breakdown=true)

from pcrcg.config import OPTIMIZERS, SCHEDULES
from pcrcg.errors import ConfigError
from pcrcg.models.datamodule import PairBatch
from pcrcg.fields import known_fields
from pcrcg.models.losses import CoarseInputs, LossConfig, PredatorLoss
from pcrcg.models.predator import build_predator
from pcrcg.registration.feature_registration import FragmentOutput

STAT_KEYS = ("loss", "circle_loss", "overlap_loss", "matchability_loss", "recall", "overlap_precision",
             "overlap_recall", "matchability_precision", "matchability_recall",
             # model=geotransformer (its coarse loss is the circle_loss)
             "point_matching_loss", "superpoint_precision", "point_precision",
             # model=cofinet (its coarse loss is also logged as circle_loss, the checkpoint monitor)
             "coarse_matching_loss", "fine_matching_loss", "coarse_precision", "fine_precision",
             # Predator's optional coarse losses (model.loss.w_coarse_*)
             "coarse_overlap_loss", "coarse_circle_loss", "coarse_recall")


def coarse_inputs(out: Any, pyr: Any, voxel_size: float) -> CoarseInputs:
    """The coarse-loss inputs of a Predator output on a stacked pyramid: each level-0 point's coarse point
    follows the decoder's nearest-upsampling indices level by level (the padding index stays padding)."""
    levels = len(pyr.points)
    assign = torch.arange(len(pyr.points[0]), device=pyr.points[0].device)
    for lv in range(levels - 1):
        n_next = len(pyr.points[lv + 1])
        up = torch.cat([pyr.upsamples[lv][:, 0], pyr.upsamples[lv].new_full((1,), n_next)])
        assign = up[assign.clamp(max=len(up) - 1)]
    n_src, _ = pyr.split(levels - 1)
    return CoarseInputs(out.coarse_logits, out.coarse_feats, pyr.points[-1], n_src, assign,
                        voxel_size * 2 ** (levels - 1))
MODELS = ("predator", "geotransformer", "cofinet")


@dataclass
class OptimConfig:
    """SGD + exponential decay per epoch (the paper's settings by default); ``name="adam"`` swaps
    the optimiser for Adam (``momentum`` then unused) for short training budgets. ``schedule="cosine"``
    replaces the per-epoch decay (``lr_decay`` then unused) by a per-step cosine from ``lr`` to 0 over the
    run's steps, after ``warmup_steps`` steps of linear warm-up (:func:`cosine_factor`)."""

    name: str = "sgd"
    lr: float = 0.005
    momentum: float = 0.98
    weight_decay: float = 1e-6
    lr_decay: float = 0.95
    encoder_lr_scale: float = 1.0  # learning-rate factor of the 2D branch
    schedule: str = "exponential"
    warmup_steps: int = 0

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any] | None) -> "OptimConfig":
        cfg = cls(**known_fields(cls, m))
        if cfg.name not in OPTIMIZERS:
            raise ConfigError("trainer.optim.name", cfg.name, " | ".join(OPTIMIZERS))
        if cfg.schedule not in SCHEDULES:
            raise ConfigError("trainer.optim.schedule", cfg.schedule, " | ".join(SCHEDULES))
        if isinstance(cfg.warmup_steps, bool) or not isinstance(cfg.warmup_steps, int) or cfg.warmup_steps < 0:
            raise ConfigError("trainer.optim.warmup_steps", cfg.warmup_steps, "an integer >= 0")
        return cfg


def cosine_factor(step: int, total: int, warmup: int = 0) -> float:
    """The learning rate's factor at optimiser step ``step`` (0-based) of ``total``: ``(step + 1) / warmup`` during
    the warm-up, then ``(1 + cos(pi * t)) / 2`` with t going from 0 at the warm-up's end to 1 at step ``total``."""
    if step < warmup:
        return (step + 1) / warmup
    t = min(1.0, (step - warmup) / max(1, total - warmup))
    return 0.5 * (1.0 + math.cos(math.pi * t))


@dataclass
class PairOutput:
    """Outputs of both fragments of a pair; ``transform`` is the data set's ground truth (src -> tgt).

    Models that register the pair themselves (GeoTransformer's local-to-global registration) add
    ``estimate`` (4, 4) source -> target and the point pairs it came from, ``estimate_pairs`` (C, 6)
    float32 (source xyz, target xyz), both in the fragments' own frames.
    """

    scene: str
    i: int
    j: int
    src: FragmentOutput
    tgt: FragmentOutput
    transform: np.ndarray
    color_coverage: float = float("nan")
    estimate: np.ndarray | None = None
    estimate_pairs: np.ndarray | None = None
    # models registered by RANSAC on their own correspondences (CoFiNet): (C, 6) float32 source xyz, target
    # xyz in the fragments' own frames, and (C,) confidences; the evaluation samples N of them by confidence
    correspondences: np.ndarray | None = None
    correspondence_scores: np.ndarray | None = None


def plain(value: Any) -> Any:
    """``value`` with OmegaConf containers, tuples, paths and numpy scalars/arrays made plain
    (dict, list, str, int, float, bool, None) — what ``torch.load(weights_only=True)`` reads."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(value, (DictConfig, ListConfig)):
            value = OmegaConf.to_container(value, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str, torch.Tensor)):
        return value
    return str(value)


def build_lifter_from(lifting: Mapping[str, Any] | None):
    """A ColorLifter from a mapping with ``projection``/``features``/``encoder2d``/``matcher2d`` nodes,
    or None when nothing is lifted (geometry only; the lifting package is then not even imported)."""
    if not lifting:
        return None
    proj = (lifting.get("projection") or {}).get("name", "none")
    feat = (lifting.get("features") or {}).get("name", "none")
    if proj == "none" or feat == "none":
        return None
    from pcrcg.lifting import build_lifter

    lifter = build_lifter(dict(lifting))
    return lifter if lifter.out_dim > 0 else None


TRAINING_2D = ("detached", "end_to_end")


def training_2d(lifting: Mapping[str, Any] | None) -> str:
    """``encoder2d.training`` of a lifting config: ``detached`` | ``end_to_end`` (the default when the
    key is absent: what checkpoints made before the setting existed did)."""
    enc = (lifting or {}).get("encoder2d") or {}
    value = str(enc.get("training", "end_to_end") if isinstance(enc, Mapping) else "end_to_end")
    if value not in TRAINING_2D:
        raise ConfigError("encoder2d.training", value, " | ".join(TRAINING_2D))
    return value


def _np(t: torch.Tensor) -> np.ndarray:
    """A tensor as a float64 numpy array on the host."""
    return t.detach().double().cpu().numpy()


def _in_frame(A: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points (K, 3) mapped by the 4x4 ``A``, as float32."""
    return (p @ A[:3, :3].T + A[:3, 3]).astype(np.float32)


class _OwnFrame(NamedTuple):
    """:meth:`PCRCGModule._own_frame_outputs`: the network's output, both fragments' outputs and the
    ground truth in the fragments' own frames, the coverage, the inverse augmentations (source,
    target) and the source's augmentation."""

    out: Any
    src: FragmentOutput
    tgt: FragmentOutput
    truth: np.ndarray
    coverage: float
    inv_s: np.ndarray
    inv_t: np.ndarray
    aug_s: np.ndarray


class PCRCGModule(L.LightningModule):
    """``PCRCGModule(model, optim=None, lifting=None)``.

    ``model``: the ``model`` config node (``conf/model/predator.yaml``; ``loss`` sub-node);
    ``optim``: :class:`OptimConfig` fields; ``lifting``: ``{"projection", "features", "encoder2d",
    "matcher2d"}`` nodes or None. ``lifter`` (optional) overrides the one built from ``lifting``.
    """

    def __init__(self, model: Mapping[str, Any], optim: Mapping[str, Any] | None = None,
                 lifting: Mapping[str, Any] | None = None, lifter: torch.nn.Module | None = None):
        super().__init__()
        self.save_hyperparameters(ignore=["lifter"])
        self.lifter = lifter if lifter is not None else build_lifter_from(lifting)
        self.training_2d = training_2d(lifting)
        lifted = int(self.lifter.out_dim) if self.lifter is not None else 0
        self.kind = str(model.get("name", "predator"))
        if self.kind not in MODELS:
            raise ConfigError("model.name", self.kind, " | ".join(MODELS))
        if self.kind == "geotransformer":
            from pcrcg.models.geotransformer import build_geotransformer

            self.net = build_geotransformer(dict(model), in_dim=1 + lifted)
        elif self.kind == "cofinet":
            from pcrcg.models.cofinet import build_cofinet

            self.net = build_cofinet(dict(model), in_dim=1 + lifted)
        else:
            self.net = build_predator(dict(model), in_dim=1 + lifted)
        self.loss_cfg = LossConfig.from_mapping(model.get("loss"))
        self.criterion = PredatorLoss(self.loss_cfg, float(model["voxel_size"]))
        self.optim_cfg = OptimConfig.from_mapping(optim)
        # the validation recall above which the matchability loss is on (0: always), as the run's official trainer
        self.matchability_after = self.loss_cfg.matchability_threshold(lifted > 0)
        gate = 1.0 if self.matchability_after <= 0 else 0.0
        self.register_buffer("matchability_gate", torch.tensor(gate))
        self.skipped_pairs = 0
        self._val_recalls: list[float] = []

    # ------------------------------------------------------------------ forward
    @property
    def in_dim(self) -> int:
        return self.net.cfg.in_dim

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        if isinstance(batch, PairBatch):
            return batch.to(device)
        return super().transfer_batch_to_device(batch, device, dataloader_idx)

    def input_features(self, batch: PairBatch) -> tuple[torch.Tensor, float]:
        """(N0, in_dim) network input of the stacked pair and the color coverage (nan without color)."""
        n0 = batch.pyramid.points[0].shape[0]
        ones = batch.pyramid.points[0].new_ones((n0, 1))
        if self.lifter is None:
            return ones, float("nan")
        sample = SimpleNamespace(src_points=batch.src_frame_points, tgt_points=batch.tgt_frame_points,
                                 src_views=batch.src_views, tgt_views=batch.tgt_views)
        from pcrcg.lifting import lift_pair

        with torch.no_grad() if self.training_2d == "detached" else contextlib.nullcontext():
            lifted = lift_pair(self.lifter, sample, getattr(batch, "matches", None), device=ones.device)
        feats = torch.cat([lifted.src_feats, lifted.tgt_feats], 0).to(ones.dtype)
        return torch.cat([ones, feats], 1), float(lifted.color_coverage)

    def forward(self, batch: PairBatch) -> tuple[Any, float]:
        with record_function("pcrcg.input_features (2D encoder + lifting)"):
            feats, coverage = self.input_features(batch)
        if self.kind == "geotransformer":  # training matches the true superpoint pairs (GeoTransformer's targets)
            return self.net(feats, batch.pyramid, batch.transform, targets=self.training), coverage
        if self.kind == "cofinet":  # training matches ground-truth node pairs (CoFiNet's), from the correspondences
            return self.net(feats, batch.pyramid, batch.corr, targets=self.training), coverage
        return self.net(feats, batch.pyramid), coverage

    def compute_stats(self, batch: PairBatch, out: Any) -> dict[str, torch.Tensor]:
        if self.kind == "geotransformer":
            from pcrcg.models.geotransformer import geotransformer_loss

            with record_function("pcrcg.losses"):
                return geotransformer_loss(out, batch.transform, self.net.cfg.loss, self.net.cfg.voxel_size)
        if self.kind == "cofinet":
            from pcrcg.models.cofinet import cofinet_loss

            with record_function("pcrcg.losses"):
                return cofinet_loss(out, batch.transform, batch.corr, self.net.cfg)
        # in training, the matchability labels are only computed while their loss is on
        need = (not self.training) or (self.loss_cfg.w_matchability > 0 and bool(self.matchability_gate > 0))
        coarse = None
        if self.loss_cfg.w_coarse_overlap > 0 or self.loss_cfg.w_coarse_circle > 0:
            coarse = coarse_inputs(out, batch.pyramid, float(self.net.cfg.voxel_size))
        with record_function("pcrcg.losses"):
            return self.criterion(out.descriptors, out.overlap_logits, out.matchability_logits, batch.pyramid.points[0],
                                  batch.n_src, batch.transform, batch.corr, self.matchability_gate, matchability=need,
                                  coarse=coarse)

    # ------------------------------------------------------------------ steps
    def training_step(self, batch: PairBatch, batch_idx: int):
        if batch.corr.shape[0] == 0:  # no overlap after subsampling: nothing to learn from this pair
            self.skipped_pairs += 1
            if self._trainer is not None:
                self.log("train/skipped_pairs", float(self.skipped_pairs), batch_size=1)
            return None
        out, coverage = self(batch)
        stats = self.compute_stats(batch, out)
        if self._trainer is not None:
            self.log_dict({f"train/{k}": stats[k].detach() for k in STAT_KEYS if k in stats}, batch_size=1)
            self.log("train/loss_step", stats["loss"].detach(), batch_size=1, prog_bar=True, logger=False)
            if coverage == coverage:
                self.log("train/color_coverage", coverage, batch_size=1)
        return stats["loss"]

    def validation_step(self, batch: PairBatch, batch_idx: int) -> None:
        if batch.corr.shape[0] == 0:
            return None
        # validation draws (the loss's sampled correspondences) from a generator of its own, seeded by the
        # batch: the same numbers every epoch, and training's random sequence is not advanced by it (an epoch's
        # last.ckpt holds the random state of its last step's end, taken before this validation ran)
        with torch.random.fork_rng(devices=[self.device] if self.device.type == "cuda" else []):
            torch.manual_seed(batch_idx)
            self._validate(batch)

    def _validate(self, batch: PairBatch) -> None:
        out, coverage = self(batch)
        stats = self.compute_stats(batch, out)
        if "recall" in stats:
            self._val_recalls.append(float(stats["recall"]))
        self.log_dict({f"val/{k}": stats[k] for k in STAT_KEYS if k in stats}, batch_size=1, on_epoch=True,
                      on_step=False)
        if coverage == coverage:
            self.log("val/color_coverage", coverage, batch_size=1, on_epoch=True, on_step=False)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Hyper-parameters as plain dicts, lists, strings and numbers, so that the checkpoint reads
        with ``torch.load(weights_only=True)`` (no code runs when it is loaded)."""
        if "hyper_parameters" in checkpoint:
            checkpoint["hyper_parameters"] = plain(checkpoint["hyper_parameters"])

    def on_validation_epoch_start(self) -> None:
        self._val_recalls = []

    def on_validation_epoch_end(self) -> None:
        recalls, self._val_recalls = self._val_recalls, []
        if self._trainer is not None and self.trainer.sanity_checking:
            return
        thr = self.matchability_after
        if recalls and thr > 0:
            # Predator: the matchability loss is on while the validation recall is above the threshold
            self.matchability_gate.fill_(1.0 if float(np.mean(recalls)) > thr else 0.0)
        if self._trainer is not None:
            self.log("val/matchability_gate", float(self.matchability_gate), batch_size=1)

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """Skip the update when a gradient is not finite (Predator skips such steps too)."""
        grads = [p.grad for p in self.parameters() if p.grad is not None]
        if not grads:
            return
        norms = torch.stack([torch.linalg.vector_norm(g.detach()) for g in grads])
        if not bool(torch.isfinite(norms).all()):
            for p in self.parameters():
                p.grad = None
            self.log("train/nonfinite_grad_skips", 1.0, batch_size=1, reduce_fx="sum")

    @torch.no_grad()
    def predict_pair(self, batch: PairBatch) -> PairOutput:
        """Outputs of both fragments in their own frames (un-doing any augmentation of the batch)."""
        if self.kind == "geotransformer":
            return self._predict_geotransformer(batch)
        if self.kind == "cofinet":
            return self._predict_cofinet(batch)
        out, coverage = self(batch)
        ns = batch.n_src
        pts = batch.pyramid.points[0]
        to_np = lambda t: t.detach().float().cpu().numpy()  # noqa: E731

        def frag(sl: slice, frame_pts: Any) -> FragmentOutput:
            fp = frame_pts if isinstance(frame_pts, np.ndarray) else to_np(frame_pts)
            return FragmentOutput(np.asarray(fp, np.float32), to_np(out.descriptors[sl]), to_np(out.overlap[sl]),
                                  to_np(out.matchability[sl]))

        src = frag(slice(0, ns), batch.src_frame_points)
        tgt = frag(slice(ns, pts.shape[0]), batch.tgt_frame_points)
        # ground truth in the fragments' own frames
        A_s, A_t = batch.src_aug.double().cpu().numpy(), batch.tgt_aug.double().cpu().numpy()
        T = np.linalg.inv(A_t) @ batch.transform.double().cpu().numpy() @ A_s
        return PairOutput(batch.scene, batch.i, batch.j, src, tgt, T, coverage)

    def _own_frame_outputs(self, batch: PairBatch, points: str) -> "_OwnFrame":
        """What GeoTransformer and CoFiNet share at prediction: the network's output on the batch and
        both fragments' :class:`FragmentOutput` in their own frames (points ``out.<src|tgt>_<points>``,
        unit fine features, the network's point scores as overlap, matchability 1), the ground truth
        in those frames, and the inverse augmentations that map the network's points back into them
        (the network never sees the batch's transform here)."""
        with record_function("pcrcg.input_features (2D encoder + lifting)"):
            feats, coverage = self.input_features(batch)
        out = self.net(feats, batch.pyramid)
        aug_s, aug_t = _np(batch.src_aug), _np(batch.tgt_aug)
        inv_s, inv_t = np.linalg.inv(aug_s), np.linalg.inv(aug_t)
        s_score, t_score = self.net.point_scores(out)

        def frag(inv: np.ndarray, pts: torch.Tensor, f: torch.Tensor, score: torch.Tensor) -> FragmentOutput:
            return FragmentOutput(_in_frame(inv, _np(pts)), _np(torch.nn.functional.normalize(f, dim=1)).astype(np.float32),
                                  _np(score).astype(np.float32), np.ones(len(pts), np.float32))

        src = frag(inv_s, getattr(out, f"src_{points}"), out.src_feats_f, s_score)
        tgt = frag(inv_t, getattr(out, f"tgt_{points}"), out.tgt_feats_f, t_score)
        truth = inv_t @ _np(batch.transform) @ aug_s
        return _OwnFrame(out, src, tgt, truth, coverage, inv_s, inv_t, aug_s)

    def _predict_geotransformer(self, batch: PairBatch) -> PairOutput:
        """Level-1 points with unit fine features (overlap: their superpoint's matching score,
        matchability 1) and the local-to-global registration, all in the fragments' own frames."""
        o = self._own_frame_outputs(batch, "fine")
        lgr = self.net.register(o.out)
        est = o.inv_t @ _np(lgr.transform) @ o.aug_s
        pairs = np.concatenate([_in_frame(o.inv_s, _np(lgr.src)), _in_frame(o.inv_t, _np(lgr.tgt))], 1)
        return PairOutput(batch.scene, batch.i, batch.j, o.src, o.tgt, o.truth, o.coverage, est, pairs)

    def _predict_cofinet(self, batch: PairBatch) -> PairOutput:
        """Level-0 points with unit fine features (overlap: their node's matching probability, matchability
        1) and the fine correspondences with their confidences, all in the fragments' own frames (the
        network never sees the batch's correspondences here)."""
        o = self._own_frame_outputs(batch, "points")
        cs, ct, conf = self.net.correspondences(o.out)
        pairs = np.concatenate([_in_frame(o.inv_s, _np(cs)), _in_frame(o.inv_t, _np(ct))], 1).reshape(-1, 6)
        return PairOutput(batch.scene, batch.i, batch.j, o.src, o.tgt, o.truth, o.coverage, correspondences=pairs,
                          correspondence_scores=_np(conf).astype(np.float32))

    def predict_step(self, batch: PairBatch, batch_idx: int, dataloader_idx: int = 0) -> PairOutput:
        return self.predict_pair(batch)

    # ------------------------------------------------------------------ optimisation
    def configure_optimizers(self):
        c = self.optim_cfg
        net_params = [p for p in self.net.parameters() if p.requires_grad]
        groups = [{"params": net_params, "lr": c.lr}]
        if self.lifter is not None and self.training_2d == "end_to_end":  # detached: the 2D net is not optimised
            lp = [p for p in self.lifter.parameters() if p.requires_grad]
            if lp:
                groups.append({"params": lp, "lr": c.lr * c.encoder_lr_scale})
        if c.name == "adam":
            opt = torch.optim.Adam(groups, lr=c.lr, weight_decay=c.weight_decay)
        else:
            opt = torch.optim.SGD(groups, lr=c.lr, momentum=c.momentum, weight_decay=c.weight_decay)
        if c.schedule == "cosine":
            total = int(self.trainer.estimated_stepping_batches)
            sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: cosine_factor(step, total, c.warmup_steps))
            return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step", "frequency": 1}}
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=c.lr_decay)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch", "frequency": 1}}
