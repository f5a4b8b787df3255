"""One run of ``python -m pcrcg.run``: validate -> skip if done -> prepare -> train -> evaluate -> log.

The stages are plain functions named in the config (``stages.prepare``, ``stages.train``,
``stages.evaluate``: dotted paths), each taking a :class:`RunContext`:

* ``prepare(ctx) -> Path``: the data set root (3DMatch layout);
* ``train(ctx) -> TrainOutput``: a checkpoint and training curves (learned methods only);
* ``evaluate(ctx) -> EvalOutput``: metrics named ``<benchmark>/<metric>_<N>``,
  ``<benchmark>/rre``, ``<benchmark>/rte``, ``color_coverage`` (recall, IR, FMR in %, RRE in
  degrees, RTE in metres: the paper's units), files to keep, and the protocol used.

The defaults below call the other stages' library functions, imported lazily so that a
stage that is not installed fails with a message naming it. Tests swap in fake stages.

Tracking (MLflow, ``logger=mlflow``): a run is tagged with its config hash and code version; when a
FINISHED run with the same hash (and code version, under ``logger.identity=config_and_code``, the
default) exists in the experiment the job is skipped. Any error after the
config is validated is recorded on the run (FAILED, ``error`` tag, ``error.txt``); a
:class:`~pcrcg.errors.ConfigError` raised there (a missing weights file) marks the run
``not_run``. In a multirun the job then returns normally so that the sweep goes on (the
multirun callback reports failures at the end); a single run re-raises.

Every run ends in a terminal state: FINISHED, FAILED (an error, also ``SystemExit``), or KILLED
(Ctrl-C, SIGTERM: the run is closed, then the interruption goes on and stops the command). A run
whose process was killed outright (SIGKILL) stays RUNNING in the store; the next launch of the same
config closes it as KILLED before it starts (:meth:`~pcrcg.tracking.tracker.RunTracker.close_stale`).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Mapping, Sequence

from omegaconf import DictConfig, OmegaConf

from pcrcg.config import (CONF_DIR, color_enabled, geometry_only, needs_training, preflight, seed_independent,
                          validate_run_config)
from pcrcg.data.layout import atomic_write_text
from pcrcg.device import cpu_threads, keep_freed_memory, resolve_device
from pcrcg.errors import ConfigError, PcrcgError, one_line
from pcrcg.tracking.git import DEFAULT_IDENTITY, code_version, same_code
from pcrcg.tracking.hashing import (COLOR_ONLY, HASH_EXCLUDE, TRAIN_HASH_EXCLUDE, config_hash, data_hash, flatten,
                                    to_plain, with_weights_digest, without, without_added)

if TYPE_CHECKING:  # pragma: no cover
    from pcrcg.tracking.tracker import RunTracker

STATUS_FILE = "pcrcg_status.json"
# keys whose overrides do not go into a run's name (they are tags or do not change the result)
NAME_EXCLUDE = ("experiment", "experiment_name", "profile", "hydra", "logger", "runtime", "paths", "stages")


class StageUnavailable(PcrcgError, RuntimeError):
    """A pipeline stage's implementation is not installed / importable."""


# --------------------------------------------------------------------------- contracts


def cpu_seconds() -> float:
    """CPU seconds (user + system) of this process, all its threads, plus those of its child processes
    that have ended (Lightning's loader processes once an epoch's loader is done)."""
    import resource

    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


class Clock:
    """Wall and CPU seconds since it was made. A stage's CPU seconds are what it costs on a core of
    its own: on a shared machine (a sweep's lanes beside each other) its wall time is that plus the
    time it waited for a core."""

    def __init__(self) -> None:
        self._wall, self._cpu = time.perf_counter(), cpu_seconds()

    def wall(self) -> float:
        return time.perf_counter() - self._wall

    def cpu(self) -> float:
        return cpu_seconds() - self._cpu

    def metrics(self, stage: str) -> dict[str, float]:
        """``{"time/<stage>_s": wall, "time/<stage>_cpu_s": cpu}``."""
        return {f"time/{stage}_s": self.wall(), f"time/{stage}_cpu_s": self.cpu()}


# what the earlier starts of a resumed training spent up to its checkpoint (pcrcg.models.train.TrainingClock),
# logged with the stage times
EARLIER_S, EARLIER_CPU_S = "time/train_earlier_s", "time/train_earlier_cpu_s"


def run_seconds(metrics: Mapping[str, float], stage: str = "total", cpu: bool = False) -> float | None:
    """A finished run's wall (or CPU) seconds of ``stage`` (``total``, ``train``, ...) from its logged ``metrics``,
    with, for ``total`` and ``train``, what the earlier starts of a resumed training spent up to its checkpoint
    (``time/train_earlier_s``): the run's cost as if it had not been interrupted. None when not logged."""
    value = metrics.get(f"time/{stage}_cpu_s" if cpu else f"time/{stage}_s")
    if value is None:
        return None
    if stage in ("total", "train"):
        value += metrics.get(EARLIER_CPU_S if cpu else EARLIER_S, 0.0)
    return float(value)


@dataclass
class TrainOutput:
    """What training leaves: the checkpoint file and curves ``{name: [v0, v1, ...]}`` (step = index)
    or ``{name: [(step, v), ...]}`` when the trainer did not log them itself."""

    checkpoint: Path | None
    history: dict[str, list] = field(default_factory=dict)
    metrics: dict[str, float] = field(default_factory=dict)
    artifacts: list[tuple[Path, str | None]] = field(default_factory=list)
    reused: bool = False
    curves_logged: bool = False  # the trainer's logger already wrote ``history`` into the run


@dataclass
class EvalOutput:
    """Evaluation results: flat metrics, files to keep ``(path, artifact folder)``, protocol facts
    (pair counts, RANSAC settings; logged as ``protocol.*`` params)."""

    metrics: dict[str, float]
    artifacts: list[tuple[Path, str | None]] = field(default_factory=list)
    protocol: dict[str, Any] = field(default_factory=dict)


@dataclass
class JobInfo:
    """Where a job runs and how it was asked for (from Hydra, or made up by a caller)."""

    output_dir: Path
    base_dir: Path
    overrides: list[str] = field(default_factory=list)
    choices: dict[str, str] = field(default_factory=dict)
    multirun: bool = False
    sweep_dir: str | None = None
    search_dirs: tuple[Path, ...] = (CONF_DIR,)


@dataclass
class RunContext:
    """What a stage receives."""

    cfg: DictConfig
    job: JobInfo
    out_dir: Path
    device: str
    data_root: Path | None = None
    checkpoint: Path | None = None
    run_id: str | None = None
    tracker: "RunTracker | None" = None
    metrics: dict[str, float] = field(default_factory=dict)

    def path(self, setting: str) -> Path:
        """A ``paths.*`` setting made absolute against the folder the command started in."""
        p = Path(str(OmegaConf.select(self.cfg, f"paths.{setting}")))
        return p if p.is_absolute() else self.job.base_dir / p

    def lightning_logger(self):
        """A Lightning ``MLFlowLogger`` writing into this run (None without tracking).

        It neither starts nor ends the run: the pipeline does both.
        """
        if self.tracker is None or self.run_id is None:
            return None
        return make_lightning_logger(self.tracker.uri, self.cfg.experiment_name, self.run_id)

    def log_metrics(self, metrics: Mapping[str, float], step: int = 0) -> None:
        if self.tracker is not None and self.run_id is not None:
            self.tracker.log_metrics(self.run_id, metrics, step)


@dataclass
class RunOutcome:
    status: str  # finished | skipped | failed | not_run | killed
    config_hash: str
    run_name: str
    run_id: str | None = None
    tracking_uri: str | None = None
    metrics: dict[str, float] = field(default_factory=dict)
    error: str | None = None
    output_dir: str | None = None
    seconds: float = 0.0

    def to_json(self) -> str:
        return json.dumps(self.__dict__, default=str, indent=1)


# --------------------------------------------------------------------------- helpers


def run_name(overrides: Sequence[str]) -> str:
    """What differs: the job's ``key=value`` overrides minus bookkeeping ones (``window_size=7``)."""
    parts = []
    for ov in overrides:
        key = ov.split("=", 1)[0].lstrip("+~")
        if key.split(".")[0].split("/")[0] in NAME_EXCLUDE:
            continue
        parts.append(ov.lstrip("+~"))
    return " ".join(parts) or "defaults"


def method_label(data: Mapping[str, Any]) -> str:
    """The paper's name for what a run computes: Predator, PCR-CG, GeoTransformer (+ PCR-CG), CoFiNet (+ PCR-CG), FPFH, ICP, ColorICP, SIFT-DLT."""
    method = data.get("method", "learned")
    if method == "learned":
        model = data.get("model") if isinstance(data.get("model"), Mapping) else {}
        if model.get("name") == "geotransformer":  # the paper's GeoTransformer table
            return "GeoTransformer + PCR-CG" if color_enabled(data) else "GeoTransformer"
        if model.get("name") == "cofinet":  # the paper's CoFiNet table (its re-trained rows)
            return "CoFiNet + PCR-CG" if color_enabled(data) else "CoFiNet"
        return "PCR-CG" if color_enabled(data) else "Predator"
    return {"fpfh": "FPFH", "icp": "ICP", "color_icp": "ColorICP", "sift_dlt": "SIFT-DLT",
            "sift_lifted": "SIFT-lifted"}.get(method, method)


def _stage(path: str) -> Callable[[RunContext], Any]:
    from hydra.utils import get_method

    return get_method(path)


def _need(module: str, attr: str, stage: str):
    """Import ``module.attr`` for ``stage`` or fail naming what is missing."""
    import importlib

    try:
        mod = importlib.import_module(module)
    except ImportError as e:
        raise StageUnavailable(f"stage '{stage}' needs {module}.{attr}, which cannot be imported: {e}") from e
    fn = getattr(mod, attr, None)
    if fn is None:
        raise StageUnavailable(f"stage '{stage}' needs {module}.{attr}, which does not exist")
    return fn


def write_status(out_dir: Path, outcome: RunOutcome) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / STATUS_FILE).write_text(outcome.to_json())


def make_lightning_logger(uri: str, experiment_name: str, run_id: str):
    """Lightning ``MLFlowLogger`` bound to an existing run, with an explicit ``tracking_uri``
    (it would read ``MLFLOW_TRACKING_URI`` at import time otherwise) and that leaves the
    run open when training ends."""
    from lightning.pytorch.loggers import MLFlowLogger

    class _OpenRunMLFlowLogger(MLFlowLogger):
        def log_hyperparams(self, params) -> None:  # the run already holds the whole config as params
            pass

        def finalize(self, status: str = "success") -> None:  # keep the run open
            if self._initialized and self._checkpoint_callback:
                self._scan_and_log_checkpoints(self._checkpoint_callback)

    return _OpenRunMLFlowLogger(experiment_name=experiment_name, tracking_uri=uri, run_id=run_id)


# --------------------------------------------------------------------------- default stages


def prepare_data(ctx: RunContext) -> Path:
    """Materialise ``data`` (generated / converted once; reused when up to date)."""
    prepare_dataset = _need("pcrcg.data.materialise", "prepare_dataset", "prepare")
    data_cfg = OmegaConf.to_container(ctx.cfg.data, resolve=True)
    assert isinstance(data_cfg, dict)
    root = Path(str(data_cfg["root"]))
    if not root.is_absolute():
        data_cfg["root"] = str(ctx.job.base_dir / root)
    # a run never replaces a data set made with other parameters (python -m pcrcg.prepare does): the refusal comes
    # before any work, where a replacement would have generated for hours and then deleted the data set held there
    return Path(prepare_dataset(data_cfg, seed=int(ctx.cfg.data_seed), replace=False))


def train_model(ctx: RunContext) -> TrainOutput:
    """Train the learned model, or reuse the checkpoint of an identical training config.

    Training happens in ``paths.checkpoints/<train hash>/train`` (the hash leaves out
    evaluation-only settings), so that (a) sweeps over evaluation settings train once, (b) a
    relaunched sweep resumes a crashed training from its ``last.ckpt``, and (c) jobs that need
    the same model wait for each other (a file lock) instead of training it twice.
    """
    from filelock import FileLock

    key = train_key(ctx.cfg)
    cache = ctx.path("checkpoints") / key
    ckpt = cache / "model.ckpt"
    hist_file = cache / "history.json"
    cache.mkdir(parents=True, exist_ok=True)
    with FileLock(str(cache / ".lock")):
        if ckpt.is_file() and bool(OmegaConf.select(ctx.cfg, "runtime.reuse_checkpoints", default=True)) \
                and _reusable_checkpoint(ckpt):
            history = json.loads(hist_file.read_text()) if hist_file.is_file() else {}
            print(f"[run] reusing checkpoint {ckpt} (same training config {key})")
            return TrainOutput(checkpoint=ckpt, history=history, reused=True)
        train = _need("pcrcg.models.train", "train", "train")
        logger = ctx.lightning_logger()
        result = train(ctx.cfg, data_root=ctx.data_root, out_dir=cache / "train", logger=logger or None,
                       device=ctx.device)
        out = result if isinstance(result, TrainOutput) else TrainOutput(
            checkpoint=Path(result["checkpoint"]) if result.get("checkpoint") else None,
            history=dict(result.get("history") or {}), metrics=dict(result.get("metrics") or {}))
        if not out.history and ctx.tracker is not None and ctx.run_id is not None:
            out.history = _curves(ctx)
            out.curves_logged = True
        if out.checkpoint is not None and Path(out.checkpoint).is_file():
            tmp = cache / f"model.ckpt.tmp-{os.getpid()}"
            shutil.copyfile(out.checkpoint, tmp)
            os.replace(tmp, ckpt)
            hist_file.write_text(json.dumps(out.history))
            (cache / "source.json").write_text(json.dumps({"run_id": ctx.run_id, "experiment": ctx.cfg.experiment_name,
                                                           "train_hash": key, "code_version": code_version()}))
            out.checkpoint = ckpt
    return out


def run_hash(cfg: DictConfig | Mapping[str, Any], exclude: Iterable[str] = HASH_EXCLUDE,
             weights_by_bytes: bool = False) -> str:
    """A run's identity: :func:`config_hash` of its config (``exclude``: ``HASH_EXCLUDE`` for the run,
    ``TRAIN_HASH_EXCLUDE`` for its training), without the ``COLOR_ONLY`` settings when it trains or
    evaluates a geometry-only learned model (``method`` learned or left out; a classical method such as
    ``sift_dlt`` reads ``matcher2d``, so its runs keep them), and without ``seed`` when nothing the run
    computes reads it (:func:`pcrcg.config.seed_independent`: ICP / ColorICP from the identity), so that a
    sweep over seeds runs it once."""
    return data_hash(hashed_config(cfg, exclude, weights_by_bytes))


def hashed_config(cfg: DictConfig | Mapping[str, Any], exclude: Iterable[str] = HASH_EXCLUDE,
                  weights_by_bytes: bool = False) -> dict[str, Any]:
    """What :func:`run_hash` hashes: the plain config without ``exclude``, without ``COLOR_ONLY`` for a
    geometry-only model, without ``seed`` when nothing reads it, with ``encoder2d.weights_digest`` (the
    tensors of the 2D weights file it names, when that file exists; ``weights_by_bytes``: the file's bytes, as
    code before aa220c7 hashed it, for reading older sweeps' stores)."""
    data = to_plain(cfg)
    if geometry_only(data):
        data = without(data, COLOR_ONLY)
    if seed_independent(data):
        data = without(data, ("seed",))
    return with_weights_digest(without_added(without(data, exclude)), by_bytes=weights_by_bytes)


def config_difference(ours: Mapping[str, Any], theirs: Mapping[str, str], limit: int = 6) -> str:
    """The settings of :func:`hashed_config` ``ours`` whose logged value differs in another run's params
    ``theirs`` (``{"a.b": "value"}``, as :meth:`RunTracker.log_params` wrote them), as one line: ``key
    (here: x, there: y)`` each, at most ``limit``; a setting that run did not log reads ``not logged``."""
    from pcrcg.tracking.tracker import MAX_PARAM_LEN

    diffs = []
    for key, value in flatten(ours).items():
        mine = str(value)[:MAX_PARAM_LEN]
        there = theirs.get(key)
        if there != mine:
            diffs.append(f"{key} (here: {mine}, there: {'not logged' if there is None else there})")
    if not diffs:
        return "no logged setting differs (the hash covers more than the run logged)"
    more = f", and {len(diffs) - limit} more" if len(diffs) > limit else ""
    return "; ".join(diffs[:limit]) + more


def train_key(cfg: DictConfig) -> str:
    """The checkpoint cache's key: the hash of the training config (evaluation-only settings left out) and,
    under ``logger.identity=config_and_code``, the code version (a model of other code is another model)."""
    key = run_hash(cfg, TRAIN_HASH_EXCLUDE)
    if same_code(identity(cfg)):
        key = config_hash({"train_hash": key, "code_version": code_version()})
    return key


def _reusable_checkpoint(ckpt: Path) -> bool:
    """A cached ``model.ckpt`` is reused only when it reads safely as a checkpoint of this project
    (:func:`pcrcg.models.train.read_checkpoint`); one that does not (planted, corrupt) is moved aside
    with a one-line warning and the model is trained again."""
    from pcrcg.errors import DataError

    read_checkpoint = _need("pcrcg.models.train", "read_checkpoint", "train")

    try:
        read_checkpoint(ckpt)
        return True
    except DataError as e:
        aside = ckpt.with_name(f"{ckpt.name}.bad-{time.strftime('%Y%m%d-%H%M%S')}")
        os.replace(ckpt, aside)
        print(f"[run] warning: not reusing {one_line(e)}; moved it to {aside.name}, training again", file=sys.stderr)
        return False


def _curves(ctx: RunContext) -> dict[str, list]:
    """Training curves the Lightning logger wrote into this run: ``{name: [(step, value)]}``."""
    assert ctx.tracker is not None and ctx.run_id is not None
    client = ctx.tracker.client
    names = [k for k in client.get_run(ctx.run_id).data.metrics if not k.startswith("time/")]
    return {k: [(m.step, m.value) for m in client.get_metric_history(ctx.run_id, k)] for k in names}


def evaluate_method(ctx: RunContext) -> EvalOutput:
    """Evaluate on both benchmarks at every sample size (learned) or run a classical baseline."""
    evaluate = _need("pcrcg.evaluation.stage", "evaluate", "evaluate")
    result = evaluate(ctx.cfg, data_root=ctx.data_root, checkpoint=ctx.checkpoint,
                      out_dir=ctx.out_dir / "eval", device=ctx.device)
    if isinstance(result, EvalOutput):
        return result
    return EvalOutput(metrics=dict(result["metrics"]),
                      artifacts=[(Path(p), a) for p, a in result.get("artifacts", [])],
                      protocol=dict(result.get("protocol", {})))


# --------------------------------------------------------------------------- the run


def identity(cfg: DictConfig) -> str:
    """``logger.identity``: whether a run of other code counts as the same run (``config``) or not."""
    return str(OmegaConf.select(cfg, "logger.identity", default=DEFAULT_IDENTITY))


def _make_2d_weights(cfg: DictConfig, job: JobInfo, data: Mapping[str, Any]) -> None:
    """``encoder2d=pri3d`` with ``encoder2d.make``: the default weights that the project's training
    stage needs are made when missing (:mod:`pcrcg.pretrain2d.make`, once per sweep). A run whose
    ``stages.train`` is its own, or whose model is already trained, makes nothing."""
    if str(cfg.stages.train) != "pcrcg.pipeline.train_model" or not needs_training(cfg):
        return
    from pcrcg.pretrain2d.make import make_missing_weights

    make_missing_weights(data, job.base_dir, log=print, hydra_dir=job.output_dir / "pretrain2d")


def run_job(cfg: DictConfig, job: JobInfo) -> RunOutcome:
    """Run one configured job end to end (see module docstring). Returns what happened.

    Steps: check the config and make the 2D weights it names, hash it, open the store (closing this
    config's stale runs), skip a config that already finished, run the stages in a tracked run
    (:func:`_execute`), then say where the results are (:func:`_conclude`)."""
    clock = Clock()
    data = to_plain(cfg)  # resolved once: interpolation is the slow part of OmegaConf
    validate_run_config(cfg, job.choices, job.search_dirs, data=data)
    _make_2d_weights(cfg, job, data)  # before the hash: it holds the weights file's digest
    h = run_hash(data)
    name = run_name(job.overrides)
    job.output_dir.mkdir(parents=True, exist_ok=True)

    tracker = _open_tracker(cfg, job, h)
    if tracker is not None and cfg.logger.skip_finished:
        skipped = _skip_if_finished(cfg, job, tracker, h, name)
        if skipped is not None:
            return skipped

    ctx = RunContext(cfg=cfg, job=job, out_dir=job.output_dir, device=resolve_device(OmegaConf.select(cfg, "runtime.device")),
                     tracker=tracker)
    outcome = _execute(ctx, data, h, name, clock)
    if outcome.status == "finished":
        _conclude(cfg, job, outcome)
    return outcome


def _open_tracker(cfg: DictConfig, job: JobInfo, h: str) -> "RunTracker | None":
    """The MLflow store of ``logger.tracking_uri`` (None when ``logger.name`` is not mlflow), with this
    config hash's stale runs (RUNNING, their process gone) closed as KILLED."""
    if cfg.logger.name != "mlflow":
        return None
    from pcrcg.tracking.tracker import RunTracker
    from pcrcg.tracking.store import resolve_tracking_uri

    uri = resolve_tracking_uri(cfg.logger.tracking_uri, job.base_dir)
    tracker = RunTracker(uri, cfg.experiment_name)
    for stale in tracker.close_stale(h):
        print(f"[run] closed stale run {stale} of config hash {h} as KILLED (its process is gone)")
    return tracker


def _skip_if_finished(cfg: DictConfig, job: JobInfo, tracker: "RunTracker", h: str, name: str) -> RunOutcome | None:
    """The outcome ``skipped`` (written to the job's folder) when a run of config hash ``h`` already
    FINISHED (with this code version under ``logger.identity=config_and_code``), else None: run it."""
    code = code_version() if same_code(identity(cfg)) else None
    done = tracker.find_finished(h, code)
    if done is not None:
        outcome = RunOutcome("skipped", h, name, done.run_id, tracker.uri, output_dir=str(job.output_dir))
        write_status(job.output_dir, outcome)
        print(f"[run] skipped {name!r}: run {done.run_id} with config hash {h}"
              f"{f' and code version {code}' if code else ''} already FINISHED in experiment {cfg.experiment_name!r}")
        return outcome
    older = tracker.find_finished(h) if code else None
    if older is not None:
        print(f"[run] run {older.run_id} with config hash {h} FINISHED with other code: running {name!r} "
              f"again with code version {code} (logger.identity=config would skip it)")
        return None
    same_job = tracker.find_finished_named(name, code)
    if same_job is not None:  # the same overrides, another config: say what changed (a remade weights file, ...)
        print(f"[run] run {same_job.run_id} of the same job {name!r} FINISHED with config hash "
              f"{same_job.config_hash}, this config is {h}: running it; what differs: "
              f"{config_difference(hashed_config(cfg), tracker.params(same_job.run_id))}")
    return None


def _execute(ctx: RunContext, data: Mapping[str, Any], h: str, name: str, clock: Clock) -> RunOutcome:
    """Start the tracked run, run the stages (:func:`_work`) and return the outcome ``finished``.

    Ctrl-C / SIGTERM: the run is closed as KILLED and the interruption re-raised. Any other error: the
    run is closed as FAILED (a :class:`ConfigError`: not run), written to the job's folder, and re-raised
    outside a sweep (always for ``SystemExit``); inside a sweep its outcome is returned."""
    from pcrcg.cli import interrupt_reason, sigterm_as_interrupt

    cfg, job, tracker = ctx.cfg, ctx.job, ctx.tracker
    uri = tracker.uri if tracker else None
    run_id = None
    stage = "start"
    try:
        # every stage with the trainer's threads, not only training: a run that reuses a checkpoint infers with
        # the threads that a run that trains does (2 torch threads beside another job on 2 cores: PCR-CG's
        # inference 2.8x slower, its training step 26x); NumPy's and Open3D's pools too (cpu_threads)
        keep_freed_memory()  # large tensors reuse the heap instead of fresh pages every step (pcrcg.device)
        with sigterm_as_interrupt(), cpu_threads(OmegaConf.select(cfg, "trainer.num_threads"), ctx.device):
            if tracker is not None:
                run_id = ctx.run_id = tracker.start(name, _tags(cfg, data, h, job))
                tracker.log_params(run_id, {**flatten(data), **_digest_params(data)})
                _log_config_files(tracker, run_id, data, job)
            for stage in _work(ctx, data, h, clock):
                pass
        metrics = ctx.metrics
        return RunOutcome("finished", h, name, run_id, uri, metrics,
                          output_dir=str(job.output_dir), seconds=clock.wall())
    except KeyboardInterrupt as e:  # Ctrl-C (also inside Lightning's fit: see models.train), SIGTERM
        reason = f"{interrupt_reason(e)} during {stage}"
        if tracker is not None and run_id is not None:
            tracker.kill(run_id, reason)
        outcome = RunOutcome("killed", h, name, run_id, uri, error=reason,
                             output_dir=str(job.output_dir), seconds=clock.wall())
        write_status(job.output_dir, outcome)
        print(f"[run] killed {name!r}: {reason} (run {run_id or '-'} closed as KILLED)", file=sys.stderr)
        raise
    except (Exception, SystemExit) as e:  # noqa: BLE001 - recorded, then re-raised or reported by the sweep
        not_run = isinstance(e, ConfigError)
        if tracker is not None and run_id is not None:
            tracker.fail(run_id, e, not_run=not_run)
        outcome = RunOutcome("not_run" if not_run else "failed", h, name, run_id, uri,
                             error=f"{type(e).__name__}: {one_line(e)}", output_dir=str(job.output_dir),
                             seconds=clock.wall())
        write_status(job.output_dir, outcome)
        print(f"[run] {outcome.status} {name!r} during {stage}: {outcome.error}", file=sys.stderr)
        if not job.multirun or isinstance(e, SystemExit):
            raise
        return outcome


def _conclude(cfg: DictConfig, job: JobInfo, outcome: RunOutcome) -> None:
    """A finished run: its status written to the job's folder, where its results are printed, and (a
    single run with ``runtime.report_on_end``) its experiment's tables written."""
    write_status(job.output_dir, outcome)
    _print_where(cfg, outcome)
    if not job.multirun and outcome.tracking_uri and OmegaConf.select(cfg, "runtime.report_on_end", default=False):
        from pcrcg.report import write_experiment_tables

        write_experiment_tables(str(cfg.experiment_name), outcome.tracking_uri,
                                OmegaConf.select(cfg, "profile.name"),
                                str(OmegaConf.select(cfg, "runtime.report_dir", default="reports")), job.base_dir, "[run]")


def _work(ctx: RunContext, data: Mapping[str, Any], h: str, clock: Clock):
    """The run's stages in order; yields the name of each stage as it starts (for messages) and
    leaves the metrics in ``ctx.metrics``. The run is finished in the store at the end. Each stage's
    wall and CPU seconds are logged as ``time/<stage>_s`` and ``time/<stage>_cpu_s`` (:class:`Clock`)."""
    cfg, tracker, run_id = ctx.cfg, ctx.tracker, ctx.run_id
    timings: dict[str, float] = {}
    yield "checks"
    preflight(data)
    yield "prepare"
    t = Clock()
    ctx.data_root = Path(_stage(cfg.stages.prepare)(ctx))
    timings.update(t.metrics("prepare"))
    yield "input checks"
    t = Clock()
    _check_inputs(ctx)
    timings.update(t.metrics("check_inputs"))
    if needs_training(cfg):
        yield "train"
        t = Clock()
        trained = _stage(cfg.stages.train)(ctx)
        timings.update(t.metrics("train"))
        # a resumed training's earlier starts (time/train_earlier_s, ..._cpu_s): with the stage times
        timings.update({k: trained.metrics.pop(k) for k in list(trained.metrics) if k.startswith("time/")})
        ctx.checkpoint = trained.checkpoint
        _log_training(ctx, trained)
    yield "evaluate"
    t = Clock()
    result: EvalOutput = _stage(cfg.stages.evaluate)(ctx)
    timings.update(t.metrics("evaluate"))
    yield "logging"
    metrics = {k: float(v) for k, v in result.metrics.items() if v is not None}
    _write_outputs(ctx, metrics, result, h)
    timings.update(clock.metrics("total"))
    # the stage times beside the metrics, also for a run without a store (logger=none)
    atomic_write_text(ctx.out_dir / "timings.json", json.dumps(timings, indent=1))
    if tracker is not None and run_id is not None:
        tracker.log_metrics(run_id, {**metrics, **timings})
        tracker.log_params(run_id, flatten(result.protocol, "protocol."))
        for path, folder in result.artifacts:
            tracker.log_artifact(run_id, path, folder)
        for f in ("metrics.json", "plots"):
            tracker.log_artifact(run_id, ctx.out_dir / f, None if f == "metrics.json" else f)
        tracker.finish(run_id)
    ctx.metrics = metrics


def _check_inputs(ctx: RunContext) -> None:
    """Every input file of the scenes the run reads, before any long work (see
    :func:`pcrcg.data.inputs.check_run_inputs`); skipped for data roots not in the layout (fakes)."""
    from pcrcg.data.inputs import check_run_inputs

    if ctx.data_root is not None:
        check_run_inputs(ctx.cfg, ctx.data_root, log=print)


def _tags(cfg: DictConfig, data: Mapping[str, Any], h: str, job: JobInfo) -> dict[str, str]:
    from pcrcg.tracking.tracker import identity_tags

    tags = {
        **identity_tags(str(cfg.experiment_name), h, str(OmegaConf.select(cfg, "profile.name", default="?"))),
        "method": str(cfg.method),
        "label": method_label(data),
        "overrides": " ".join(job.overrides),
    }
    if seed_independent(data):
        tags["seed_independent"] = "true"
    if job.sweep_dir:
        tags["sweep_dir"] = job.sweep_dir
    return tags


def _digest_params(data: Mapping[str, Any]) -> dict[str, str]:
    """``encoder2d.weights_digest``, logged beside the config: part of the run's identity (the weights
    file's bytes), so that a relaunch can say that a remade file is why a finished job runs again."""
    digest = with_weights_digest({"encoder2d": dict(data.get("encoder2d") or {})})["encoder2d"].get("weights_digest")
    return {"encoder2d.weights_digest": digest} if digest else {}


def _log_config_files(tracker: "RunTracker", run_id: str, data: Mapping[str, Any], job: JobInfo) -> None:
    """Resolved config and overrides (and Hydra's own .hydra/ files when present) as artifacts."""
    cdir = job.output_dir / "config"
    cdir.mkdir(parents=True, exist_ok=True)
    (cdir / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(dict(data))))
    (cdir / "overrides.yaml").write_text("".join(f"- {o}\n" for o in job.overrides) or "[]\n")
    tracker.log_artifact(run_id, cdir, "config")
    hydra_dir = job.output_dir / ".hydra"
    if hydra_dir.is_dir():
        tracker.log_artifact(run_id, hydra_dir, "config/hydra")


def _log_training(ctx: RunContext, trained: TrainOutput) -> None:
    if ctx.tracker is None or ctx.run_id is None:
        return
    if trained.history and not trained.curves_logged:
        ctx.tracker.log_history(ctx.run_id, trained.history)
    if trained.metrics:
        ctx.tracker.log_metrics(ctx.run_id, trained.metrics)
    if trained.checkpoint is None or not bool(ctx.cfg.logger.log_checkpoint):
        pass
    elif trained.reused:  # the run that trained it holds the file: point to it instead of a copy
        src = Path(trained.checkpoint).parent / "source.json"
        source = json.loads(src.read_text()) if src.is_file() else {}
        ctx.tracker.set_tags(ctx.run_id, {"checkpoint_reused": str(trained.checkpoint),
                                          "checkpoint_run": source.get("run_id") or "unknown"})
        ctx.tracker.log_text(ctx.run_id, json.dumps({"checkpoint": str(trained.checkpoint), **source}, indent=1),
                             "checkpoint/reused_from.json")
    else:
        ctx.tracker.log_artifact(ctx.run_id, trained.checkpoint, "checkpoint")
    for path, folder in trained.artifacts:
        ctx.tracker.log_artifact(ctx.run_id, path, folder)


def _write_outputs(ctx: RunContext, metrics: Mapping[str, float], result: EvalOutput, h: str) -> None:
    """``metrics.json`` and ``plots/recall_vs_points.png`` in the job's output folder."""
    from pcrcg.cli import strict_json

    (ctx.out_dir / "metrics.json").write_text(strict_json(  # NaN (no registered pair: RRE) as null
        {"config_hash": h, "metrics": metrics, "protocol": result.protocol}, indent=1))
    try:
        from pcrcg.plots.recall import plot_run_recall

        plot_run_recall(metrics, ctx.out_dir / "plots" / "recall_vs_points.png",
                        title=f"{ctx.cfg.experiment_name}: {run_name(ctx.job.overrides)}")
    except ImportError:  # pragma: no cover - matplotlib missing
        pass


def _print_where(cfg: DictConfig, outcome: RunOutcome) -> None:
    lines = [f"[run] finished {outcome.run_name!r} in {outcome.seconds:.1f} s (config hash {outcome.config_hash})"]
    import re

    for key in sorted(outcome.metrics):
        if re.search(r"/rr(_\d+)?$", key) or key == "color_coverage":
            v = outcome.metrics[key]
            lines.append(f"      {key} = {v:.2f}" if not math.isnan(v) else f"      {key} = nan")
    lines.append(f"      outputs: {outcome.output_dir}")
    if outcome.tracking_uri:
        from pcrcg.tracking.store import ui_command

        lines.append(f"      MLflow run {outcome.run_id} in experiment {cfg.experiment_name!r}")
        lines.append(f"      open the UI: {ui_command(outcome.tracking_uri)}")
    print("\n".join(lines))
