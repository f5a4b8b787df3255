"""Training and inference entry points of the models stage.

* :func:`train` ``(cfg, data_root=None, out_dir=None, logger=None, device=None, datamodule=None,
  lifter=None) -> {"checkpoint", "last_checkpoint", "history", "metrics", "neighbor_limits"}``: trains
  the Lightning module described by a root config (nodes ``model``, ``trainer``, ``data.root``,
  ``seed`` and, for color, ``projection``/``features``/``encoder2d``/``matcher2d``); ``checkpoint``
  is the best checkpoint (the last one when no validation ran). Checkpoints go to
  ``<out_dir>/checkpoints``: ``best.ckpt`` (lowest ``trainer.monitor``) and ``last.ckpt`` (every
  ``trainer.checkpoint_every_n_steps`` steps, every epoch end, and on a crash or Ctrl-C between steps); a
  run whose ``last.ckpt`` exists resumes from it, bit for bit the uninterrupted run (:class:`LastCheckpoint`,
  :class:`GlobalRngState`, :class:`~pcrcg.models.datamodule.EpochSampler`; metric
  ``train/resumed_from_step``). Without a logger, curves go to
  ``<out_dir>/logs/version_<k>/metrics.csv`` (one version per start). This is the contract of
  :func:`pcrcg.pipeline.train_model`.
* :func:`load_module` ``(checkpoint, device=None) -> PCRCGModule`` in eval mode.
* :func:`read_checkpoint` ``(path) -> dict``: a checkpoint read without the ability to run code
  (``torch.load(weights_only=True)``: tensors, plain containers and primitives only; the module
  saves its hyper-parameters as such) and checked to be one of this project's; a crafted pickle, a
  text file, a state-dict-only or corrupt file is a :class:`~pcrcg.errors.DataError` naming it. A
  ``last.ckpt`` that fails this check is moved aside (``last.ckpt.bad-<time>``) with a one-line
  warning and training starts afresh, so that it does not block its config on every relaunch.
* :func:`infer` ``(checkpoint_or_module, root, split, device=None, max_pairs=None) -> Iterator[PairOutput]``:
  per-pair outputs on a benchmark (``3DMatch``/``3DLoMatch``) or split, each fragment in its own frame.
* :func:`infer_clouds` ``(module, src_points, tgt_points, src_views=(), tgt_views=()) -> PairOutput``:
  the same for two user clouds.
* :func:`save_pair_output` / :func:`load_pair_output`: one ``.npz`` per pair.
"""

from __future__ import annotations

import copy
import math
import os
import random
import signal
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger, Logger
from omegaconf import DictConfig, OmegaConf

from pcrcg.data.layout import evenly
from pcrcg.device import resolve_device
from pcrcg.errors import ConfigError, DataError, one_line
from pcrcg.fields import lookup
from pcrcg.models.datamodule import PairDataModule, pair_from_clouds
from pcrcg.models.module import PairOutput, PCRCGModule, build_lifter_from
from pcrcg.pipeline import EARLIER_CPU_S, EARLIER_S, cpu_seconds
from pcrcg.registration.feature_registration import FragmentOutput
from pcrcg.safeload import load_tensors

LIFTING_NODES = ("projection", "features", "encoder2d", "matcher2d")


def _container(node: Any) -> Any:
    if isinstance(node, DictConfig):
        return OmegaConf.to_container(node, resolve=True)
    return copy.deepcopy(node)


def _get(cfg: Any, key: str, default: Any = None) -> Any:
    if isinstance(cfg, DictConfig):
        return _container(OmegaConf.select(cfg, key, default=default))
    return copy.deepcopy(lookup(cfg, key, default))


def lifting_section(cfg: Any) -> dict[str, Any] | None:
    """The nodes the projection module is built from, or None when the config has none."""
    out = {k: _get(cfg, k) for k in LIFTING_NODES if _get(cfg, k) is not None}
    return out or None


def _checkpoint_dir(out_dir: Path) -> Path:
    return out_dir / "checkpoints"


class LastCheckpoint(Callback):
    """Keeps ``last.ckpt`` current: every ``every_n_steps`` optimiser steps, at the end of every
    epoch (also when ``max_steps`` ends one early) and when training stops on an exception or Ctrl-C,
    so an interrupted run resumes where it stopped. Written to a temporary file, then renamed.

    Only states a run resumes from exactly are written: not between a batch and the validation due
    after it (Lightning would resume past that validation), not from inside a training step. A run
    resumed from ``last.ckpt`` is then bit for bit the uninterrupted one (with :class:`GlobalRngState`
    and the data module's :class:`~pcrcg.models.datamodule.EpochSampler`)."""

    def __init__(self, path: Path, every_n_steps: int | None = None):
        self.path = Path(path)
        self.every = int(every_n_steps or 0)
        self._saved_step = -1
        self._closed_epoch = -1

    def save(self, trainer: L.Trainer) -> None:
        if trainer.sanity_checking or trainer.global_step == 0 or trainer.global_step == self._saved_step:
            return
        if self.before_validation(trainer):
            # Lightning resumes from such a state without the validation that was due (and so without its
            # say in best.ckpt): keep the previous last.ckpt, a few steps back but exact
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f"{self.path.stem}.tmp-{os.getpid()}.ckpt")
        # the whole state (optimiser, loops, callbacks) to resume from, said explicitly: Lightning logs a line
        # at every save when weights_only is left unset (reading it back is weights_only=True all the same)
        trainer.save_checkpoint(str(tmp), weights_only=False)
        if trainer.is_global_zero:
            os.replace(tmp, self.path)
        self._saved_step = trainer.global_step

    def before_validation(self, trainer: L.Trainer) -> bool:
        """Whether the last finished batch is one that a validation follows (the epoch's last, or every
        ``val_check_batch``-th) and the epoch has not been closed since (validation then epoch end)."""
        done = int(trainer.fit_loop.epoch_loop.batch_progress.current.processed)
        if done == 0 or self._closed_epoch == trainer.current_epoch or not trainer.enable_validation:
            return False
        if done >= trainer.num_training_batches:
            return True
        every = trainer.val_check_batch
        return isinstance(every, int) and every > 0 and done % every == 0

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # resumed: the checkpoint's step is saved already (Lightning may replay that epoch's end)
        self._saved_step = trainer.global_step if trainer.global_step > 0 else -1

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if self.every and trainer.global_step % self.every == 0:
            self.save(trainer)

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._closed_epoch = -1

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._closed_epoch = trainer.current_epoch
        self.save(trainer)

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        fit = trainer.fit_loop.epoch_loop.batch_progress.current
        # inside a training step the weights may be half-updated and the random state is mid-step
        where = (f"during step {trainer.global_step + 1}" if fit.started != fit.processed
                 else f"after step {trainer.global_step}, before its validation" if self.before_validation(trainer)
                 else None)
        if where is None:
            self.save(trainer)
            return
        kept = f"left at step {self._saved_step}" if self._saved_step > 0 else "not written yet"
        print(f"[train] {type(exception).__name__} {where}: last.ckpt {kept} (a relaunch resumes from there, "
              "exactly)", file=sys.stderr, flush=True)


class GlobalRngState(Callback):
    """Puts the global random generators (torch, CUDA, numpy, Python) in checkpoints and, in a run
    resumed from one, sets them back when training starts: the model's own draws (the loss's sampled
    correspondences) continue the uninterrupted run's sequence. The data draw from none of them
    (:class:`~pcrcg.models.datamodule.EpochSampler`). Stored as tensors and plain lists, so the
    checkpoint still loads with ``weights_only=True``."""

    def __init__(self) -> None:
        self._pending: dict[str, Any] | None = None
        self._snapshot: dict[str, Any] | None = None

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        # the state between two steps: what a checkpoint written later on a crash must hold
        self._snapshot = self.current()

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._restore()
        self._snapshot = self.current()

    def state_dict(self) -> dict[str, Any]:
        return self._snapshot if self._snapshot is not None else self.current()

    @staticmethod
    def current() -> dict[str, Any]:
        """The global generators' states now."""
        kind, keys, pos, has_gauss, cached = np.random.get_state()
        version, internal, gauss = random.getstate()
        return {"torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
                "numpy": [str(kind), [int(k) for k in keys], int(pos), int(has_gauss), float(cached)],
                "python": [int(version), list(internal), gauss]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._pending = dict(state)

    def _restore(self) -> None:
        state, self._pending = self._pending, None
        if not state:
            return
        torch.set_rng_state(state["torch"])
        if state.get("cuda") and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(state["cuda"])
        kind, keys, pos, has_gauss, cached = state["numpy"]
        np.random.set_state((kind, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
        version, internal, gauss = state["python"]
        random.setstate((version, tuple(internal), gauss))


class TrainingClock(Callback):
    """The wall and CPU seconds of a training across its starts. A checkpoint holds the seconds spent until it was
    written; a run resumed from it starts from them, so that :meth:`earlier` is what the earlier starts cost up to
    that checkpoint (what an interrupted start ran after its last checkpoint is lost, and not counted). Plain floats
    in the checkpoint (it still loads with ``weights_only=True``)."""

    def __init__(self) -> None:
        self._earlier = (0.0, 0.0)
        self._start: tuple[float, float] | None = None
        self.restored = False  # the checkpoint resumed from held this clock's state (code before 2026-12-08: not)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._start = (time.perf_counter(), cpu_seconds())

    def earlier(self) -> tuple[float, float]:
        """(wall, cpu) seconds of the earlier starts, up to the checkpoint this start resumed from ((0, 0): none)."""
        return self._earlier

    def state_dict(self) -> dict[str, float]:
        wall, cpu = self._earlier
        if self._start is not None:
            wall, cpu = wall + time.perf_counter() - self._start[0], cpu + cpu_seconds() - self._start[1]
        return {"wall_s": float(wall), "cpu_s": float(cpu)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        def seconds(key: str) -> float:  # provenance only: a value that is not a number counts as none
            try:
                value = float(state.get(key, 0.0))
            except (TypeError, ValueError):
                return 0.0
            return value if math.isfinite(value) and value >= 0 else 0.0

        self._earlier = (seconds("wall_s"), seconds("cpu_s"))
        self.restored = True


def build_trainer(tcfg: Mapping[str, Any], out_dir: Path, logger: Logger | Sequence[Logger] | bool | None = None,
                  extra_callbacks: Sequence[Callback] = ()) -> tuple[L.Trainer, "LastCheckpoint", ModelCheckpoint]:
    """The Lightning trainer with ``last.ckpt`` / ``best.ckpt``; returns (trainer, last_cb, best_cb)."""
    ckdir = _checkpoint_dir(out_dir)
    last_cb = LastCheckpoint(ckdir / "last.ckpt", tcfg.get("checkpoint_every_n_steps"))
    best_cb = ModelCheckpoint(dirpath=ckdir, filename="best", monitor=tcfg.get("monitor", "val/circle_loss"),
                              mode=tcfg.get("monitor_mode", "min"), save_top_k=1, save_last=False,
                              enable_version_counter=False, auto_insert_metric_name=False)
    if logger is None:
        # one version folder per (re)start: a resumed run does not overwrite the curves so far
        logger = CSVLogger(str(out_dir), name="logs") if tcfg.get("csv_logger", True) else False
    # GlobalRngState before LastCheckpoint: its snapshot of a step's end is taken before that step's save
    callbacks: list[Callback] = [best_cb, GlobalRngState(), last_cb, *extra_callbacks]
    if logger:
        from lightning.pytorch.callbacks import LearningRateMonitor

        callbacks.append(LearningRateMonitor(logging_interval="epoch"))
    max_steps = tcfg.get("max_steps")
    # PairBatch moves itself (PCRCGModule.transfer_batch_to_device): the notice about it is noise
    warnings.filterwarnings("ignore", message=".*overridden `transfer_batch_to_device`.*")
    trainer = L.Trainer(
        default_root_dir=str(out_dir),
        accelerator=tcfg.get("accelerator", "auto"),
        devices=tcfg.get("devices", 1),
        num_nodes=int(tcfg.get("num_nodes", 1) or 1),
        strategy=tcfg.get("strategy") or "auto",
        sync_batchnorm=bool(tcfg.get("sync_batchnorm", False)),
        precision=tcfg.get("precision", "32-true"),
        max_epochs=tcfg.get("max_epochs", 1),
        max_steps=-1 if max_steps in (None, 0) else int(max_steps),
        limit_train_batches=tcfg.get("limit_train_batches") or 1.0,
        limit_val_batches=tcfg.get("limit_val_batches") if tcfg.get("limit_val_batches") is not None else 1.0,
        val_check_interval=tcfg.get("val_check_interval") or 1.0,
        check_val_every_n_epoch=tcfg.get("check_val_every_n_epoch", 1),
        log_every_n_steps=int(tcfg.get("log_every_n_steps", 5)),
        num_sanity_val_steps=0,
        gradient_clip_val=tcfg.get("gradient_clip_val"),
        enable_progress_bar=bool(tcfg.get("progress_bar", True)),
        enable_model_summary=False,
        logger=logger,
        callbacks=callbacks,
    )
    return trainer, last_cb, best_cb


class HistoryCallback(Callback):
    """Keeps the logged curves in memory: ``{name: [(step, value), ...]}`` (train every logging step,
    val every validation)."""

    def __init__(self) -> None:
        self.history: dict[str, list[tuple[int, float]]] = {}

    def _take(self, trainer: L.Trainer, prefix: str) -> None:
        step = int(trainer.global_step)
        for k, v in trainer.callback_metrics.items():
            if k.startswith(prefix) and not k.endswith("_step"):
                try:
                    val = float(v)
                except (TypeError, ValueError):
                    continue
                curve = self.history.setdefault(k, [])
                if not curve or curve[-1][0] != step:
                    curve.append((step, val))

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if trainer.global_step % max(1, trainer.log_every_n_steps) == 0:
            self._take(trainer, "train/")

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.sanity_checking:
            self._take(trainer, "val/")


def _accelerator(device: str | None, tcfg: Mapping[str, Any]) -> dict[str, Any]:
    if device in (None, "", "auto"):
        return dict(tcfg)
    dev = str(device)
    acc = "gpu" if dev.startswith("cuda") else dev
    return {**tcfg, "accelerator": acc}


def train(cfg: Any, data_root: str | Path | None = None, out_dir: str | Path | None = None,
          logger: Logger | Sequence[Logger] | bool | None = None, device: str | None = None,
          datamodule: PairDataModule | None = None, lifter: torch.nn.Module | None = None,
          callbacks: Sequence[Callback] = ()) -> dict[str, Any]:
    """Train (or resume) the model of a root config.

    ``data_root`` overrides ``cfg.data.root``; ``out_dir`` overrides ``cfg.trainer.dir`` (default
    ``outputs/train``); ``logger``: Lightning logger(s) (default: CSV curves in ``out_dir/logs``);
    ``device``: ``cpu`` / ``cuda`` / ``auto``. Returns ``{"checkpoint": best (or last) checkpoint path,
    "last_checkpoint", "history": {name: [(step, value)]} (empty when a logger was given: it has
    the curves), "metrics": summary numbers}``.
    """
    t0 = time.perf_counter()
    mcfg = _get(cfg, "model")
    tcfg = _accelerator(device, _get(cfg, "trainer") or {})
    if not mcfg:
        raise ConfigError("model", None, "a model config node (conf/model/predator.yaml)")
    from pcrcg.models.module import MODELS

    if mcfg.get("name", "predator") not in MODELS:
        raise ConfigError("model.name", mcfg.get("name"), " | ".join(MODELS))
    out = Path(out_dir or tcfg.get("dir") or "outputs/train")
    out.mkdir(parents=True, exist_ok=True)
    if tcfg.get("num_threads"):
        # on a shared CPU, fewer torch threads than cores avoids OpenMP spinning (measured: 1 thread
        # 1.6 s/step where 2 threads took 7-20 s with the 2 cores oversubscribed)
        torch.set_num_threads(int(tcfg["num_threads"]))
    L.seed_everything(int(_get(cfg, "seed", 0) or 0), workers=True, verbose=False)

    lifting = lifting_section(cfg)
    lifter = lifter if lifter is not None else build_lifter_from(lifting)
    n_views = int(lifter.cfg.n_views_needed) if lifter is not None and hasattr(lifter, "cfg") else 0
    match_fn = lifter.match if lifter is not None and getattr(lifter.cfg, "projection", "") == "explicit" else None
    if datamodule is None:
        root = data_root if data_root is not None else _get(cfg, "data.root")
        datamodule = PairDataModule.from_config(root, mcfg, tcfg, n_views=n_views, match_fn=match_fn,
                                                seed=int(_get(cfg, "seed", 0) or 0))
    datamodule.setup("fit")
    mcfg["neighbor_limits"] = list(datamodule.limits or ())
    module = PCRCGModule(mcfg, optim=tcfg.get("optim"), lifting=lifting, lifter=lifter)

    hist = HistoryCallback()
    external_logger = logger not in (None, False)
    clock = TrainingClock()
    trainer, last_cb, best_cb = build_trainer(tcfg, out, logger, [hist, clock, *callbacks])
    last = _checkpoint_dir(out) / "last.ckpt"
    resumed_at = _resumable(last, module) if tcfg.get("resume", True) and last.is_file() else None
    _fit(trainer, module, datamodule, str(last) if resumed_at is not None else None)
    best = best_cb.best_model_path
    metrics = {"train/global_step": float(trainer.global_step), "train/epochs": float(trainer.current_epoch),
               "train/seconds": time.perf_counter() - t0, "train/skipped_pairs": float(module.skipped_pairs),
               "train/in_dim": float(module.in_dim),
               # provenance: resumed from last.ckpt at this step (0: not); bit for bit the uninterrupted run
               "train/resumed_from_step": float(resumed_at or 0)}
    if resumed_at and clock.restored:
        # what the earlier starts spent up to that checkpoint (a run's time/train_s counts this start only)
        metrics[EARLIER_S], metrics[EARLIER_CPU_S] = clock.earlier()
    if best_cb.best_model_score is not None:
        metrics[f"best/{best_cb.monitor}"] = float(best_cb.best_model_score)
    return {"checkpoint": best if best and Path(best).is_file() else str(last), "last_checkpoint": str(last),
            "history": {} if external_logger else hist.history, "metrics": metrics,
            "neighbor_limits": list(datamodule.limits or ())}


class _ExceptionRecorder(Callback):
    """Keeps the exceptions Lightning saw (module level: ``ddp_spawn`` pickles the callbacks)."""

    def __init__(self) -> None:
        self.seen: list[BaseException] = []

    def on_exception(self, trainer, pl_module, exception):  # noqa: ANN001
        self.seen.append(exception)


def _fit(trainer: L.Trainer, module: PCRCGModule, datamodule: PairDataModule, ckpt: str | None) -> None:
    """``trainer.fit`` that gives a Ctrl-C back as ``KeyboardInterrupt``: Lightning catches it, saves
    (``LastCheckpoint.on_exception``), ignores further SIGINTs and calls ``sys.exit(1)``, which would
    look like an ordinary failure to the caller and leave Ctrl-C ignored for the rest of the process."""
    recorder = _ExceptionRecorder()
    seen = recorder.seen
    trainer.callbacks.append(recorder)
    handler = signal.getsignal(signal.SIGINT)
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt, weights_only=True)
    except SystemExit:
        interrupt = next((e for e in seen if isinstance(e, KeyboardInterrupt)), None)
        if interrupt is None:
            raise
        raise interrupt.with_traceback(None) from None
    finally:
        if handler is not None:
            try:
                signal.signal(signal.SIGINT, handler)
            except ValueError:  # pragma: no cover - not the main thread
                pass


def _resumable(last: Path, module: PCRCGModule) -> int | None:
    """The step ``last.ckpt`` resumes from, or None when it cannot be resumed from: such a file (corrupt,
    crafted, another model) is moved aside with a one-line warning, and training starts afresh."""
    try:
        ck = read_checkpoint(last)
        if "optimizer_states" not in ck or "global_step" not in ck:
            raise DataError(last, "holds no training state (optimizer_states, global_step): not a last.ckpt")
        _check_state_dict(module, ck["state_dict"], last)
        return int(ck["global_step"])
    except DataError as e:
        aside = last.with_name(f"{last.name}.bad-{time.strftime('%Y%m%d-%H%M%S')}")
        os.replace(last, aside)
        print(f"[train] warning: cannot resume: {one_line(e)}; moved it to {aside.name} and starting afresh",
              file=sys.stderr, flush=True)
        return None


# --------------------------------------------------------------------------- checkpoints


def read_checkpoint(checkpoint: str | Path) -> dict[str, Any]:
    """A checkpoint of this project, read with ``torch.load(weights_only=True)`` (no code runs).

    It must hold a ``state_dict`` and ``hyper_parameters`` with the ``model`` node; anything else
    is a DataError naming the file (one line).
    """
    path = Path(checkpoint)
    if not path.is_file():
        raise ConfigError("checkpoint", str(path), "an existing checkpoint file written by pcrcg training")
    ck = load_tensors(path)
    if isinstance(ck, Mapping) and ck and all(isinstance(v, torch.Tensor) for v in ck.values()):
        raise DataError(path, "is a bare state dict (weights without the model's hyper_parameters): give a "
                              "checkpoint written by pcrcg training (checkpoints/<hash>/model.ckpt, best.ckpt)")
    if not isinstance(ck, Mapping) or not isinstance(ck.get("state_dict"), Mapping):
        raise DataError(path, "holds no 'state_dict': not a checkpoint of pcrcg training")
    hp = ck.get("hyper_parameters")
    if not isinstance(hp, Mapping) or not isinstance(hp.get("model"), Mapping):
        raise DataError(path, "holds a state dict without the model's hyper_parameters (a bare state dict?): "
                              "give a checkpoint written by pcrcg training (checkpoints/<hash>/model.ckpt)")
    return dict(ck)


def _check_state_dict(module: torch.nn.Module, sd: Mapping[str, Any], path: Path) -> None:
    own = module.state_dict()
    missing = [k for k in own if k not in sd]
    unexpected = [k for k in sd if k not in own]
    shapes = [k for k in own if k in sd and hasattr(sd[k], "shape") and tuple(sd[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or shapes:
        first = (missing or unexpected or shapes)[0]
        raise DataError(path, f"does not fit the model ({len(missing)} missing, {len(unexpected)} unexpected, "
                              f"{len(shapes)} mis-shaped weights; first: {first})")


# --------------------------------------------------------------------------- inference


def load_module(checkpoint: str | Path, device: str | torch.device | None = None) -> PCRCGModule:
    """The trained module in eval mode. A 2D encoder is rebuilt without its pretrained file (its
    trained weights are in the checkpoint), so inference needs nothing but the checkpoint."""
    path = Path(checkpoint)
    ckpt = read_checkpoint(path)
    hp = ckpt["hyper_parameters"]
    lifting = copy.deepcopy(hp.get("lifting"))
    if lifting and lifting.get("encoder2d"):
        lifting["encoder2d"] = {**lifting["encoder2d"], "name": "scratch", "weights": None}
    try:
        module = PCRCGModule(dict(hp["model"]), optim=hp.get("optim"), lifting=lifting)
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(path, f"its hyper_parameters do not describe a model ({type(e).__name__}: "
                              f"{one_line(e, 160)})") from None
    _check_state_dict(module, ckpt["state_dict"], path)
    module.load_state_dict(ckpt["state_dict"])
    dev = torch.device(resolve_device(device))  # None: auto
    return module.to(dev).eval()


def inference_datamodule(module: PCRCGModule, root: str | Path | None, **kw: Any) -> PairDataModule:
    """A data module with the module's own voxel size, levels and neighbour limits."""
    m = module.hparams["model"]
    n_views = int(module.lifter.cfg.n_views_needed) if module.lifter is not None else 0
    match_fn = module.lifter.match if module.lifter is not None and module.lifter.cfg.projection == "explicit" else None
    dm = PairDataModule(root=root, n_views=n_views, voxel_size=m["voxel_size"], num_layers=m["num_layers"],
                        conv_radius=m.get("conv_radius", 2.5), max_points=m.get("max_points", 30000),
                        overlap_radius=(m.get("loss") or {}).get("overlap_radius", 1.5),
                        neighbor_limits=m.get("neighbor_limits"), match_fn=match_fn, **kw)
    if dm.limits is None:
        dm.setup("predict")
    return dm


def infer(model: str | Path | PCRCGModule, root: str | Path, split: str, device: str | torch.device | None = None,
          max_pairs: int | None = None, progress: bool = True, cache_dir: str | Path | None = None
          ) -> Iterator[PairOutput]:
    """Per-pair outputs (each fragment in its own frame) for ``split`` of the data set at ``root``
    (``cache_dir``: the neighbour pyramids' folder kept between runs, ``trainer.cache_dir``)."""
    from tqdm import tqdm

    module = model if isinstance(model, PCRCGModule) else load_module(model, device)
    module.eval()
    dm = inference_datamodule(module, root, cache_dir=cache_dir)
    ds = dm.dataset(split)
    collate = dm.collate(train=False)
    chosen = list(range(len(ds))) if max_pairs is None else evenly(list(range(len(ds))), int(max_pairs))
    for k in tqdm(chosen, desc=f"infer {split}", disable=not progress):
        batch = collate([ds[k]]).to(module.device)
        yield module.predict_pair(batch)


def infer_clouds(module: PCRCGModule, src_points: np.ndarray, tgt_points: np.ndarray, src_views: Sequence = (),
                 tgt_views: Sequence = ()) -> PairOutput:
    """Outputs for two user clouds (any density; subsampled to the model's voxel size)."""
    dm = inference_datamodule(module, None, datasets={"train": [pair_from_clouds(src_points, tgt_points)]})
    batch = dm.collate(train=False)([pair_from_clouds(src_points, tgt_points, None, src_views, tgt_views)])
    return module.eval().predict_pair(batch.to(module.device))


def save_pair_output(out: PairOutput, path: str | Path) -> Path:
    """One ``.npz`` with ``src_*`` / ``tgt_*`` arrays, ``transform`` and the pair's identity."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {f"src_{k}": v for k, v in out.src.as_dict().items()}
    arrays.update({f"tgt_{k}": v for k, v in out.tgt.as_dict().items()})
    if out.estimate is not None:  # a model's own registration (GeoTransformer's LGR)
        arrays["estimate"] = np.asarray(out.estimate)
        arrays["estimate_pairs"] = np.asarray(out.estimate_pairs, np.float32).reshape(-1, 6)
    if out.correspondences is not None:  # a model's own correspondences (CoFiNet's)
        arrays["correspondences"] = np.asarray(out.correspondences, np.float32).reshape(-1, 6)
        arrays["correspondence_scores"] = np.asarray(out.correspondence_scores, np.float32).reshape(-1)
    np.savez_compressed(path, transform=out.transform, scene=np.array(out.scene), i=out.i, j=out.j,
                        color_coverage=out.color_coverage, **arrays)
    return path


def load_pair_output(path: str | Path) -> PairOutput:
    with np.load(path, allow_pickle=False) as z:
        frag = lambda p: FragmentOutput(z[f"{p}_points"], z[f"{p}_descriptors"], z[f"{p}_overlap"],  # noqa: E731
                                        z[f"{p}_matchability"])
        extra = (z["estimate"], z["estimate_pairs"]) if "estimate" in z.files else (None, None)
        corr = (z["correspondences"], z["correspondence_scores"]) if "correspondences" in z.files else (None, None)
        return PairOutput(str(z["scene"]), int(z["i"]), int(z["j"]), frag("src"), frag("tgt"), z["transform"],
                          float(z["color_coverage"]), *extra, *corr)
