"""The 2D pretraining run: data -> view pairs -> contrastive training -> held-out matching -> checkpoint.

:func:`pretrain` ``(cfg, base_dir=None, log=print, progress=None) -> dict`` takes the composed
``conf/pretrain2d.yaml`` (a DictConfig or plain dict) and returns the result that
``python -m pcrcg.pretrain2d`` prints as its last line::

    {"checkpoint": PATH, "loss_start": ..., "loss_end": ..., "match_acc_scratch": ...,
     "match_acc_pretrained": ..., "eval_loss_scratch": ..., "eval_loss_pretrained": ...,
     "steps": ..., "seconds": ..., "pairs": <training pairs>, "eval_pairs": ..., "eval_points": ...,
     "pixel_threshold": ..., "image_size": [H, W], "arch": ..., "init": ..., "eval_split": ...,
     "config_hash": ..., "reused": false, "run_id": ... | null}

* ``match_acc_scratch`` is the encoder *before* training (the seeded random init for
  ``encoder2d=scratch``; ``init`` says which), ``match_acc_pretrained`` after; both on the same
  held-out pixels (drawn once with the seed).
* ``loss_start`` / ``loss_end``: mean training loss over the first / last ``train.loss_window`` steps.
* An existing ``out`` checkpoint with the same config hash is reused (``reused: true``) unless
  ``force=true``.

Every setting is checked before the data is touched (:func:`check_settings`, ConfigError naming it);
a missing data root with ``prepare=false`` or missing frames are DataErrors naming the file.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from pcrcg.config import OPTIMIZERS
from pcrcg.data.layout import Layout
from pcrcg.device import keep_freed_memory, resolve_device
from pcrcg.errors import ConfigError, DataError
from pcrcg.fields import lookup
from pcrcg.pretrain2d.frames import FrameCache, FrameSequence, list_sequences, load_sequence
from pcrcg.vision.encoders import ARCHS, INITS, ResUNet, build_encoder, save_pri3d_checkpoint
from pcrcg.vision.pretrain import (
    PixelMatches,
    color_jitter,
    crop_pair,
    gather_pixels,
    info_nce,
    match_accuracy,
    pixel_correspondences,
    relative_pose,
    sample_matches,
    select_view_pairs,
)

EXPERIMENT = "pretrain2d"
HASH_EXCLUDE = ("hydra", "logger", "paths", "runtime", "out", "force", "data.workers", "train.num_threads",
                "encoder2d.memo_mb")
SCHEDULES = ("cosine", "constant")
HOLDOUT = "holdout"


# --------------------------------------------------------------------------- settings


def _int(cfg: Mapping, key: str, low: int, allow_none: bool = False) -> int | None:
    v = lookup(cfg, key)
    if v is None and allow_none:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or v < low:
        raise ConfigError(key, v, f"an integer >= {low}" + (" or null" if allow_none else ""))
    return int(v)


def _num(cfg: Mapping, key: str, low: float, high: float = math.inf, low_open: bool = False) -> float:
    v = lookup(cfg, key)
    ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
    ok = ok and (v > low if low_open else v >= low) and v <= high
    if not ok:
        lo = f"> {low}" if low_open else f">= {low}"
        raise ConfigError(key, v, f"a number {lo}" + (f" and <= {high}" if math.isfinite(high) else ""))
    return float(v)


@dataclass(frozen=True)
class Settings:
    """The checked values of ``conf/pretrain2d.yaml`` that the run uses."""

    seed: int
    image_size: tuple[int, int] | None
    min_gap: int
    max_gap: int
    min_overlap: float
    max_overlap: float
    overlap_stride: int
    frame_stride: int
    max_per_scene: int | None
    depth_tolerance: float
    depth_tolerance_rel: float
    train_splits: tuple[str, ...]
    steps: int
    batch_pairs: int
    crop: tuple[int, int] | None
    points: int
    min_points: int
    temperature: float
    symmetric: bool
    optimizer: str
    lr: float
    weight_decay: float
    lr_schedule: str
    warmup_steps: int
    color_jitter: float
    loss_window: int
    num_threads: int | None
    eval_split: str
    holdout_fraction: float
    eval_pairs: int
    eval_points: int
    pixel_threshold: float


def check_settings(cfg: Mapping[str, Any]) -> Settings:
    """Check every setting of the pretraining config (plain dict); ConfigError names the first bad one."""
    size = lookup(cfg, "image_size")
    if size is not None:
        if (not isinstance(size, (list, tuple)) or len(size) != 2
                or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 32 for s in size)):
            raise ConfigError("image_size", size, "null or [H, W] with integers >= 32")
        size = (int(size[0]), int(size[1]))
    crop = lookup(cfg, "train.crop")
    if crop is not None:
        if (not isinstance(crop, (list, tuple)) or len(crop) != 2
                or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 32 for c in crop)
                or (size is not None and (crop[0] > size[0] or crop[1] > size[1]))):
            raise ConfigError("train.crop", crop, f"null or [h, w] with integers >= 32, at most image_size {size}")
        crop = (int(crop[0]), int(crop[1]))
    enc = lookup(cfg, "encoder2d") or {}
    if enc.get("name", "scratch") not in INITS:
        raise ConfigError("encoder2d.name", enc.get("name"), " | ".join(INITS))
    if enc.get("arch", "resnet18") not in ARCHS:
        raise ConfigError("encoder2d.arch", enc.get("arch"), " | ".join(ARCHS))
    _int(cfg, "encoder2d.out_dim", 1)
    min_ov = _num(cfg, "pairs.min_overlap", 0.0, 1.0)
    max_ov = _num(cfg, "pairs.max_overlap", 0.0, 1.0)
    if max_ov < min_ov:
        raise ConfigError("pairs.max_overlap", max_ov, f"a number >= pairs.min_overlap ({min_ov})")
    min_gap = _int(cfg, "pairs.min_frame_gap", 1)
    max_gap = _int(cfg, "pairs.max_frame_gap", 1)
    if max_gap < min_gap:
        raise ConfigError("pairs.max_frame_gap", max_gap, f"an integer >= pairs.min_frame_gap ({min_gap})")
    splits = lookup(cfg, "train.splits")
    if isinstance(splits, str):
        splits = [splits]
    if not splits or not all(isinstance(s, str) and s for s in splits):
        raise ConfigError("train.splits", splits, "a non-empty list of split names (train, val, test)")
    opt = lookup(cfg, "train.optimizer")
    if opt not in OPTIMIZERS:
        raise ConfigError("train.optimizer", opt, " | ".join(sorted(OPTIMIZERS)))  # "adam | sgd", as this message always read
    sched = lookup(cfg, "train.lr_schedule")
    if sched not in SCHEDULES:
        raise ConfigError("train.lr_schedule", sched, " | ".join(SCHEDULES))
    eval_split = lookup(cfg, "eval.split")
    if not isinstance(eval_split, str) or not eval_split:
        raise ConfigError("eval.split", eval_split, f"a split name (val, test) or {HOLDOUT}")
    for key in ("train.symmetric",):
        if not isinstance(lookup(cfg, key), bool):
            raise ConfigError(key, lookup(cfg, key), "true or false")
    seed = lookup(cfg, "seed")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError("seed", seed, "an integer")
    return Settings(
        seed=int(seed), image_size=size, min_gap=min_gap, max_gap=max_gap, min_overlap=min_ov, max_overlap=max_ov,
        overlap_stride=_int(cfg, "pairs.overlap_stride", 1), frame_stride=_int(cfg, "pairs.frame_stride", 1),
        max_per_scene=_int(cfg, "pairs.max_per_scene", 1, allow_none=True),
        depth_tolerance=_num(cfg, "correspondence.depth_tolerance", 0.0, low_open=True),
        depth_tolerance_rel=_num(cfg, "correspondence.depth_tolerance_rel", 0.0),
        train_splits=tuple(splits), steps=_int(cfg, "train.steps", 0), batch_pairs=_int(cfg, "train.batch_pairs", 1),
        crop=crop,
        points=_int(cfg, "train.points", 2), min_points=_int(cfg, "train.min_points", 2),
        temperature=_num(cfg, "train.temperature", 0.0, low_open=True), symmetric=bool(lookup(cfg, "train.symmetric")),
        optimizer=opt, lr=_num(cfg, "train.lr", 0.0, low_open=True), weight_decay=_num(cfg, "train.weight_decay", 0.0),
        lr_schedule=sched, warmup_steps=_int(cfg, "train.warmup_steps", 0),
        color_jitter=_num(cfg, "train.color_jitter", 0.0, 0.9), loss_window=_int(cfg, "train.loss_window", 1),
        num_threads=_int(cfg, "train.num_threads", 1, allow_none=True), eval_split=eval_split,
        holdout_fraction=_num(cfg, "eval.holdout_fraction", 0.0, 0.9, low_open=True),
        eval_pairs=_int(cfg, "eval.pairs", 1), eval_points=_int(cfg, "eval.points", 1),
        pixel_threshold=_num(cfg, "eval.pixel_threshold", 0.0, low_open=True),
    )


# --------------------------------------------------------------------------- data


@dataclass(frozen=True)
class ViewPair:
    """Frames ``a`` and ``b`` (indices into sequence ``seq``'s frames) and their two-way overlap."""

    seq: int
    a: int
    b: int
    overlap: float


def load_split_sequences(layout: Layout, splits: Sequence[str], s: Settings, log: Callable[[str], None],
                         setting: str, cache: FrameCache | None = None) -> list[FrameSequence]:
    """All RGB-D sequences of the scenes of ``splits`` (every ``frame_stride``-th frame), indexed."""
    out = []
    for split in splits:
        f = layout.split_file(split)
        if not f.is_file():
            raise DataError(f, f"split file of {setting}={split!r} is missing")
        for scene in layout.scenes(split):
            for seq, ids in list_sequences(layout, scene):
                seqf = load_sequence(layout, scene, seq, ids[:: s.frame_stride], s.image_size, s.overlap_stride,
                                     cache)
                if seqf.skipped:
                    log(f"[pretrain2d] {scene}/{seq}: skipped {seqf.skipped} frames with an unusable pose")
                out.append(seqf)
    return out


def scene_pairs(seqs: Sequence[FrameSequence], s: Settings, rng: np.random.Generator,
                max_per_scene: int | None) -> list[ViewPair]:
    """View pairs of every sequence (:func:`select_view_pairs`), at most ``max_per_scene`` per scene."""
    by_scene: dict[str, list[ViewPair]] = {}
    for k, sq in enumerate(seqs):
        found = select_view_pairs(list(sq.coarse_depths), sq.poses, sq.coarse_K, s.min_gap, s.max_gap,
                                  s.min_overlap, s.max_overlap, 1, s.depth_tolerance, s.depth_tolerance_rel)
        by_scene.setdefault(sq.scene, []).extend(ViewPair(k, a, b, ov) for a, b, ov in found)
    out = []
    for scene in sorted(by_scene):
        pairs = by_scene[scene]
        if max_per_scene is not None and len(pairs) > max_per_scene:
            idx = np.sort(rng.choice(len(pairs), max_per_scene, replace=False))
            pairs = [pairs[i] for i in idx]
        out.extend(pairs)
    return out


def pair_matches(sq: FrameSequence, a: int, b: int, s: Settings) -> PixelMatches:
    """Visible correspondences from frame a into frame b of a sequence (at the input size)."""
    return pixel_correspondences(sq.frame(a)[1], sq.K, sq.frame(b)[1], sq.K, relative_pose(sq.poses[a], sq.poses[b]),
                                 s.depth_tolerance, s.depth_tolerance_rel)


@dataclass
class EvalItem:
    """One held-out pair: fixed query pixels and their true target positions."""

    seq: int
    a: int
    b: int
    matches: PixelMatches


def eval_items(seqs: Sequence[FrameSequence], pairs: Sequence[ViewPair], s: Settings,
               rng: np.random.Generator) -> list[EvalItem]:
    """``eval.pairs`` held-out pairs with ``eval.points`` visible source pixels each (drawn once)."""
    if len(pairs) > s.eval_pairs:
        idx = np.sort(rng.choice(len(pairs), s.eval_pairs, replace=False))
        pairs = [pairs[i] for i in idx]
    out = []
    for p in pairs:
        m = pair_matches(seqs[p.seq], p.a, p.b, s)
        if len(m) >= 1:
            out.append(EvalItem(p.seq, p.a, p.b, sample_matches(m, s.eval_points, rng)))
    return out


def to_images(colors: Sequence[np.ndarray], device: torch.device) -> torch.Tensor:
    """uint8 (H, W, 3) images -> (B, 3, H, W) float in [0, 1] on ``device``."""
    x = torch.from_numpy(np.ascontiguousarray(np.stack(colors))).to(device)
    return x.permute(0, 3, 1, 2).float().div_(255.0)


@torch.no_grad()
def evaluate(model: ResUNet, seqs: Sequence[FrameSequence], items: Sequence[EvalItem], s: Settings,
             device: torch.device) -> dict[str, float]:
    """Held-out nearest-neighbour matching accuracy and InfoNCE of ``model`` (eval mode)."""
    was_training = model.training
    model.eval()
    accs, losses, n_hits, n_all = [], [], 0, 0
    try:
        for it in items:
            sq = seqs[it.seq]
            (ca, _), (cb, db) = sq.frame(it.a), sq.frame(it.b)
            feats = model(to_images([ca, cb], device))
            acc, hits = match_accuracy(feats[0], feats[1], it.matches.src_pix, it.matches.tgt_uv, db > 0,
                                       s.pixel_threshold)
            accs.append(acc)
            n_hits += int(hits.sum())
            n_all += len(hits)
            if len(it.matches) >= 2:
                losses.append(float(info_nce(gather_pixels(feats[0], it.matches.src_pix),
                                             gather_pixels(feats[1], it.matches.tgt_pix), s.temperature,
                                             s.symmetric)))
    finally:
        model.train(was_training)
    return {"match_acc": n_hits / max(n_all, 1), "match_acc_pair_mean": float(np.mean(accs)) if accs else float("nan"),
            "loss": float(np.mean(losses)) if losses else float("nan")}


def lr_factor(step: int, s: Settings) -> float:
    """Learning-rate multiplier at ``step``: linear warm-up, then constant or cosine down to 0.1."""
    if s.warmup_steps and step < s.warmup_steps:
        return (step + 1) / s.warmup_steps
    if s.lr_schedule == "constant" or s.steps <= s.warmup_steps:
        return 1.0
    t = (step - s.warmup_steps) / max(1, s.steps - s.warmup_steps)
    return 0.1 + 0.9 * 0.5 * (1.0 + math.cos(math.pi * min(1.0, t)))


def train_step(model: ResUNet, opt: torch.optim.Optimizer, seqs: Sequence[FrameSequence], batch: Sequence[ViewPair],
               s: Settings, rng: np.random.Generator, gen: torch.Generator, device: torch.device) -> float | None:
    """One optimiser step on ``batch`` (random direction per pair); returns the loss (None: no usable pair)."""
    colors, matches = [], []
    for p in batch:
        sq = seqs[p.seq]
        a, b = (p.a, p.b) if rng.random() < 0.5 else (p.b, p.a)
        m = pair_matches(sq, a, b, s)
        ca, cb = sq.frame(a)[0], sq.frame(b)[0]
        if s.crop is not None:
            cropped = crop_pair(m, ca.shape[:2], cb.shape[:2], s.crop, rng)
            if cropped is None:
                continue
            (va, ua), (vb, ub), m = cropped
            ca = ca[va:va + s.crop[0], ua:ua + s.crop[1]]
            cb = cb[vb:vb + s.crop[0], ub:ub + s.crop[1]]
        m = sample_matches(m, s.points, rng)
        if len(m) < s.min_points:
            continue
        colors += [ca, cb]
        matches.append(m)
    if not matches:
        return None
    x = color_jitter(to_images(colors, device), s.color_jitter, gen)
    feats = model(x)
    loss = torch.stack([info_nce(gather_pixels(feats[2 * k], m.src_pix), gather_pixels(feats[2 * k + 1], m.tgt_pix),
                                 s.temperature, s.symmetric) for k, m in enumerate(matches)]).mean()
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return float(loss.detach())


def make_optimizer(model: ResUNet, s: Settings) -> torch.optim.Optimizer:
    params = [p for p in model.parameters() if p.requires_grad]
    if s.optimizer == "sgd":
        return torch.optim.SGD(params, lr=s.lr, momentum=0.9, weight_decay=s.weight_decay)
    return torch.optim.Adam(params, lr=s.lr, weight_decay=s.weight_decay)


# --------------------------------------------------------------------------- the run


def _plain(cfg: Any) -> dict[str, Any]:
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        data = OmegaConf.to_container(cfg, resolve=True)
    else:
        import copy

        data = copy.deepcopy(dict(cfg))
    assert isinstance(data, dict)
    data.pop("hydra", None)
    return data


def _abs(path: Any, base: Path) -> Path:
    p = Path(str(path)).expanduser()
    return p if p.is_absolute() else base / p


def pretrained_on(cfg: Mapping[str, Any]) -> str:
    """What the pretraining sees, as ``encoder2d.pretrained_on`` names it: ``<data.name>-seed<data_seed>`` for
    generated data (another seed = other rooms than the benchmark's seed 0), ``<data.name>`` for real frames."""
    name = str(lookup(cfg, "data.name", "data"))
    if lookup(cfg, "data.synth") is not None:  # generated
        return f"{name}-seed{int(cfg.get('data_seed', 0) or 0)}"
    return name


def default_checkpoint(cfg: Mapping[str, Any], base: Path) -> Path:
    """``<paths.checkpoints>/pretrain2d/<pretrained_on>-<profile.name>/pri3d_<arch>.pth`` (or ``out``)."""
    if cfg.get("out"):
        return _abs(cfg["out"], base)
    root = _abs(lookup(cfg, "paths.checkpoints", "checkpoints"), base)
    profile = lookup(cfg, "profile.data_profile") or lookup(cfg, "profile.name", "default")  # official: paper's
    tag = f"{pretrained_on(cfg)}-{profile}"
    return root / "pretrain2d" / tag / f"pri3d_{lookup(cfg, 'encoder2d.arch', 'resnet18')}.pth"


def _reusable(path: Path, h: str) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 - an unreadable file is simply retrained
        return None
    meta = ck.get("meta") if isinstance(ck, Mapping) else None
    if isinstance(meta, Mapping) and meta.get("config_hash") == h and isinstance(meta.get("result"), Mapping):
        return dict(meta["result"])
    return None


def _window_mean(values: Sequence[float], window: int, last: bool) -> float:
    if not values:
        return float("nan")
    w = max(1, min(window, len(values)))
    return float(np.mean(values[-w:] if last else values[:w]))


def pretrain(cfg: Any, base_dir: str | Path | None = None, log: Callable[[str], None] = print,
             progress: bool | None = None) -> dict[str, Any]:
    """Run the 2D pretraining described by ``cfg`` (``conf/pretrain2d.yaml``); see the module docstring.

    Steps: the settings checked and a checkpoint of the same config reused (:func:`_reuse_checkpoint`); the data
    (:func:`_load_data`); the seeded model trained and evaluated in a tracked run (:func:`_train_and_evaluate`,
    :func:`_summary`); the checkpoint written (:func:`_save`)."""
    from pcrcg.tracking.hashing import config_hash

    t0 = time.time()
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    data = _plain(cfg)
    s = check_settings(data)
    h = config_hash(data, HASH_EXCLUDE)
    out = default_checkpoint(data, base)
    reused = None if data.get("force", False) else _reuse_checkpoint(out, h, log)
    if reused is not None:
        return reused
    if s.num_threads:
        torch.set_num_threads(s.num_threads)
    keep_freed_memory()
    show = bool(lookup(data, "runtime.progress", True)) if progress is None else progress
    device = torch.device(resolve_device(lookup(data, "runtime.device")))
    d = _load_data(data, s, base, device, log)

    torch.manual_seed(s.seed)  # the model's init, after the data's draws
    enc_cfg = dict(data.get("encoder2d") or {})
    model = build_encoder(enc_cfg).to(device)
    tracker, run_id = _start_tracking(data, h, base, out, log)
    try:
        result = _train_and_evaluate(model, d.train_seqs, d.eval_seqs, d.pairs, d.items, s, device, show, log,
                                     tracker, run_id)
        result.update(_summary(d, s, model, enc_cfg, data, h, out, run_id))
        result["seconds"] = round(time.time() - t0, 1)
        _save(model, out, data, h, d.root, result)
        if tracker is not None:
            _finish_tracking(tracker, run_id, result, out)
    except BaseException as e:
        if tracker is not None:
            tracker.fail(run_id, e)
        raise
    return result


def _reuse_checkpoint(out: Path, h: str, log: Callable[[str], None]) -> dict[str, Any] | None:
    """The result of the checkpoint at ``out`` when it was made by this config (hash ``h``), marked reused;
    None: train."""
    prev = _reusable(out, h)
    if prev is None:
        return None
    log(f"[pretrain2d] {out} holds this config's checkpoint (hash {h}); reusing it (force=true retrains)")
    return {**prev, "checkpoint": str(out), "reused": True}


@dataclass
class _Data:
    """What a pretraining reads: the data set's root, the training and held-out sequences, the name of the
    held-out set (a split or ``holdout``), the training view pairs and the held-out items."""

    root: Path
    train_seqs: list[FrameSequence]
    eval_seqs: list[FrameSequence]
    eval_split: str
    pairs: list[ViewPair]
    items: list[EvalItem]


def _load_data(data: Mapping[str, Any], s: Settings, base: Path, device: torch.device,
               log: Callable[[str], None]) -> _Data:
    """The data (:func:`_data_root`, :func:`_sequences`, :func:`_training_pairs` drawn with ``seed``,
    :func:`_held_out_items`), and a line that says how much of it there is."""
    root = _data_root(data, base, log)
    layout = Layout(root)
    rng = np.random.default_rng(s.seed)
    cache = FrameCache(int(lookup(data, "runtime.cache_frames", 4000) or 0))
    train_seqs, eval_seqs, eval_split = _sequences(layout, s, log, cache)
    pairs = _training_pairs(train_seqs, s, rng, root)
    items = _held_out_items(eval_seqs, s, root)
    n_frames = sum(len(q) for q in train_seqs)
    log(f"[pretrain2d] {root}: {len(pairs)} training pairs from {n_frames} frames of {len(train_seqs)} sequences; "
        f"{len(items)} held-out pairs ({eval_split}); images {s.image_size or 'native'}; device {device}")
    return _Data(root, train_seqs, eval_seqs, eval_split, pairs, items)


def _summary(d: _Data, s: Settings, model: ResUNet, enc_cfg: Mapping[str, Any], data: Mapping[str, Any], h: str,
             out: Path, run_id: str | None) -> dict[str, Any]:
    """What the result says besides the training's figures: the checkpoint, the data, the model, the run."""
    return {
        "checkpoint": str(out), "pairs": len(d.pairs), "eval_pairs": len(d.items),
        "eval_points": int(sum(len(it.matches) for it in d.items)), "pixel_threshold": s.pixel_threshold,
        "image_size": list(s.image_size) if s.image_size else None, "arch": model.arch,
        "init": str(enc_cfg.get("name", "scratch")), "eval_split": d.eval_split, "config_hash": h,
        "pretrained_on": pretrained_on(data), "data_root": str(d.root),
        "reused": False, "run_id": run_id,
    }


def _data_root(data: Mapping[str, Any], base: Path, log: Callable[[str], None]) -> Path:
    """The data set's root (``data.root`` against ``base``): prepared first (``prepare=true``), else used as it is
    (a DataError when it does not exist)."""
    data_cfg = dict(data["data"])
    data_cfg["root"] = str(_abs(data_cfg.get("root", ""), base))
    if data.get("prepare", True):
        from pcrcg.data.materialise import prepare_dataset

        return Path(prepare_dataset(data_cfg, seed=int(data.get("data_seed", 0)), log=log))
    root = Path(data_cfg["root"])
    if not root.is_dir():
        raise DataError(root, "data root (data.root) does not exist (prepare=false uses it as it is)")
    return root


def _sequences(layout: Layout, s: Settings, log: Callable[[str], None],
               cache: FrameCache) -> tuple[list[FrameSequence], list[FrameSequence], str]:
    """The training sequences of ``train.splits``, the held-out sequences and the name of what they are: the
    scenes of ``eval.split``, or (``holdout``, also when that split has no scenes) the last
    ``eval.holdout_fraction`` of every training sequence, cut off the training sequences."""
    train_seqs = load_split_sequences(layout, s.train_splits, s, log, "train.splits", cache)
    if not train_seqs:
        raise ConfigError("train.splits", list(s.train_splits),
                          f"splits with scenes in {layout.root / 'splits'} (these have none)")
    eval_split = s.eval_split
    eval_scenes = [] if eval_split == HOLDOUT else (
        layout.scenes(eval_split) if layout.split_file(eval_split).is_file() else [])
    if eval_split != HOLDOUT and not eval_scenes:
        log(f"[pretrain2d] split {eval_split!r} has no scenes: evaluating on held-out frames instead "
            f"(the last {s.holdout_fraction:.0%} of every training sequence)")
        eval_split = HOLDOUT
    if eval_split != HOLDOUT:
        return train_seqs, load_split_sequences(layout, [eval_split], s, log, "eval.split", cache), eval_split
    eval_seqs = []
    for k, sq in enumerate(train_seqs):
        cut = len(sq) - max(2, int(round(len(sq) * s.holdout_fraction)))
        if cut < 2:
            raise DataError(layout.rgbd_dir(sq.scene) / sq.seq,
                            f"only {len(sq)} frames: too few to hold some out (eval.holdout_fraction)")
        eval_seqs.append(sq.subset(range(cut, len(sq))))
        train_seqs[k] = sq.subset(range(cut))
    return train_seqs, eval_seqs, eval_split


def _training_pairs(train_seqs: Sequence[FrameSequence], s: Settings, rng: np.random.Generator,
                    root: Path) -> list[ViewPair]:
    """The training view pairs (at most ``pairs.max_per_scene`` a scene, drawn with ``rng``); a ConfigError
    naming the pair bounds when none is found."""
    pairs = scene_pairs(train_seqs, s, rng, s.max_per_scene)
    if not pairs:
        raise ConfigError("pairs.min_overlap", s.min_overlap,
                          f"bounds that some training frame pairs meet (none of {sum(len(q) for q in train_seqs)} "
                          f"frames in {root} pair up with overlap in [{s.min_overlap}, {s.max_overlap}] and "
                          f"frame gap in [{s.min_gap}, {s.max_gap}])")
    return pairs


def _held_out_items(eval_seqs: Sequence[FrameSequence], s: Settings, root: Path) -> list[EvalItem]:
    """The held-out view pairs and their pixel matches (seeded by ``seed`` + 1 and + 2); a ConfigError naming
    ``eval.split`` when none is found."""
    eval_pairs_all = scene_pairs(eval_seqs, s, np.random.default_rng(s.seed + 1), None)
    items = eval_items(eval_seqs, eval_pairs_all, s, np.random.default_rng(s.seed + 2))
    if not items:
        raise ConfigError("eval.split", s.eval_split, f"a split (or {HOLDOUT}) whose frames pair up (no held-out "
                                                      f"view pairs found in {root})")
    return items


def _save(model: ResUNet, out: Path, data: Mapping[str, Any], h: str, root: Path, result: Mapping[str, Any]) -> None:
    """The weights and what made them (config hash, profile, data, image size, the config, the result, the
    git commit) to ``out``."""
    from pcrcg.tracking.git import git_info
    from pcrcg.tracking.hashing import flatten

    meta = {"config_hash": h, "profile": lookup(data, "profile.name"), "data_root": str(root),
            "image_size": result["image_size"], "created": time.strftime("%Y-%m-%d %H:%M:%S"),
            "config": flatten({k: v for k, v in data.items() if k not in ("hydra",)}), "result": dict(result)}
    meta["git_sha"] = git_info()[0]
    save_pri3d_checkpoint(model, out, meta)


def _train_and_evaluate(model: ResUNet, train_seqs, eval_seqs, pairs, items, s: Settings, device, show: bool,
                        log, tracker, run_id) -> dict[str, Any]:
    from tqdm import tqdm

    before = evaluate(model, eval_seqs, items, s, device)
    log(f"[pretrain2d] before training: held-out match accuracy {before['match_acc']:.3f}, "
        f"InfoNCE {before['loss']:.3f}")
    model.train()
    opt = make_optimizer(model, s)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: lr_factor(k, s))
    rng = np.random.default_rng(s.seed + 3)
    gen = torch.Generator().manual_seed(s.seed + 4)
    losses: list[float] = []
    skipped = 0
    bar = tqdm(range(s.steps), desc="pretrain2d", disable=not show, dynamic_ncols=True, mininterval=1.0)
    for step in bar:
        idx = rng.choice(len(pairs), s.batch_pairs, replace=len(pairs) < s.batch_pairs)
        loss = train_step(model, opt, train_seqs, [pairs[i] for i in idx], s, rng, gen, device)
        sched.step()
        if loss is None:
            skipped += 1
            continue
        losses.append(loss)
        if step % 10 == 0 or step == s.steps - 1:
            bar.set_postfix(loss=f"{np.mean(losses[-10:]):.3f}")
    bar.close()
    after = evaluate(model, eval_seqs, items, s, device)
    log(f"[pretrain2d] after {s.steps} steps: held-out match accuracy {after['match_acc']:.3f} "
        f"(before {before['match_acc']:.3f}), InfoNCE {after['loss']:.3f} (before {before['loss']:.3f})")
    if tracker is not None and losses:
        tracker.log_history(run_id, {"train/loss": losses})
    return {"loss_start": _window_mean(losses, s.loss_window, False),
            "loss_end": _window_mean(losses, s.loss_window, True),
            "match_acc_scratch": before["match_acc"], "match_acc_pretrained": after["match_acc"],
            "eval_loss_scratch": before["loss"], "eval_loss_pretrained": after["loss"],
            "steps": s.steps, "skipped_steps": skipped}


# --------------------------------------------------------------------------- tracking


def _start_tracking(data: Mapping[str, Any], h: str, base: Path, out: Path, log) -> tuple[Any, str | None]:
    if lookup(data, "logger.name", "none") != "mlflow":
        return None, None
    from pcrcg.tracking.hashing import flatten
    from pcrcg.tracking.tracker import RunTracker, identity_tags
    from pcrcg.tracking.store import resolve_tracking_uri

    uri = resolve_tracking_uri(lookup(data, "logger.tracking_uri"), base)
    tracker = RunTracker(uri, EXPERIMENT)
    profile = str(lookup(data, "profile.name", "?"))
    arch = str(lookup(data, "encoder2d.arch", "?"))
    run_id = tracker.start(f"pri3d_{arch}-{profile}", {**identity_tags(EXPERIMENT, h, profile), "checkpoint": str(out)})
    params = {k: v for k, v in flatten(data).items() if not k.startswith(("hydra.", "profile."))}
    tracker.log_params(run_id, params)
    log(f"[pretrain2d] MLflow run {run_id} in {uri} (experiment {EXPERIMENT})")
    return tracker, run_id


def _finish_tracking(tracker: Any, run_id: str | None, result: Mapping[str, Any], out: Path) -> None:
    metrics = {k: float(v) for k, v in result.items()
               if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))}
    tracker.log_metrics(run_id, metrics, step=int(result.get("steps", 0)))
    tracker.set_tags(run_id, {"checkpoint": str(out), "checkpoint_mb": f"{out.stat().st_size / 2**20:.1f}"})
    import json

    tracker.log_text(run_id, json.dumps(dict(result), indent=1, default=str), "result.json")
    tracker.finish(run_id)
