"""Tracked runs evaluated again on another data set: ``python -m pcrcg.evaluate mode=tracked``.

Every FINISHED run of the named MLflow experiments that trained a model (``method=learned``, or
``icp``/``color_icp`` with ``icp_init=learned``), and every run of a classical method (FPFH, ICP or
ColorICP from the identity, the SIFT methods: no model, the same method on the other root), is evaluated
on the test benchmarks of another data root with the evaluation stage of a run
(:func:`pcrcg.evaluation.stage.evaluate`), under the run's own logged
config (registration and protocol settings, every N, seed) with ``data.root`` replaced and
``eval.max_pairs`` null (every pair of the other root). The results go into the same run:

* metrics ``<name>/<benchmark>/<key>`` with the keys the run logs (``3DMatch/rr_5000`` ->
  ``<name>/3DMatch/rr_5000``; a color model's ``color_coverage`` -> ``<name>/color_coverage``), logged
  last: their presence marks a run as done (skipped on the next call unless ``force``);
* artifacts ``<name>/pairs/<benchmark>.csv`` (:mod:`pcrcg.evaluation.pairs`),
  ``<name>/estimates/<benchmark>/<N>/<scene>/est.log`` and ``<name>/evaluation/metrics.json``;
* tags ``<name>.data_root`` (``<root> params_hash=<manifest's hash>``), ``<name>.checkpoint`` (the file
  evaluated and where it was found), ``<name>.code_version`` (the code that evaluated it, which may be
  newer than the run's ``code_version``).

The run's model is found, in order (:func:`find_checkpoint`): (1) its checkpoint artifact
``checkpoint/model.ckpt`` (the copy the store keeps: immutable, survives a cleaned cache); (2) a run
that reused a model (tags ``checkpoint_run``, ``checkpoint_reused``): the training run's artifact, else the
cached file if its ``source.json`` names that training run; (3) the checkpoint cache
``<paths.checkpoints>/*/model.ckpt`` whose ``source.json`` names this run (``logger.log_checkpoint=false``).
A cached file is only taken when its ``source.json`` says which run trained it: a cache entry can be
retrained after its file went bad, and would then be another model. Files are read with
:func:`pcrcg.models.train.read_checkpoint` (``torch.load(weights_only=True)``: no code runs).

Everything is checked before the first evaluation: the data root and its benchmarks, the store and
the experiments, every run's config and checkpoint (a corrupt one is an error naming it; a missing one
skips that run), and the views of the fragments for color models.
"""

from __future__ import annotations

import json
import re
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence
from urllib.parse import unquote, urlparse

from pcrcg.config import CLASSICAL_METHODS as CLASSICAL
from pcrcg.data.layout import BENCHMARKS, Layout
from pcrcg.errors import ConfigError, DataError

CONFIG_ARTIFACT = "config/config.yaml"
CHECKPOINT_ARTIFACT = "checkpoint/model.ckpt"
CLASSICAL_FROM = "none: a classical method, run again on the other root"
SOURCE_FILE = "source.json"
TAG_REUSED = "checkpoint_reused"
TAG_REUSED_RUN = "checkpoint_run"
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
# the keys of a run's metrics shown in the JSON line (all of them are logged)
SHOWN = re.compile(r"/(rr|fmr|ir)(_\d+|_lgr|_lgr_ransac)?$|color_coverage$")


@dataclass
class Candidate:
    """A tracked run to evaluate: its identity, logged config (plain dicts) and model file."""

    run_id: str
    experiment: str
    run_name: str
    config: dict[str, Any]
    checkpoint: Path | None  # None: a classical method (no model)
    checkpoint_from: str
    n_views: int = 0

    @property
    def model(self) -> str:
        """What is evaluated, for logs and tags: the model file and where it was found, or the classical method."""
        if self.checkpoint is None:
            return f"method {self.config.get('method')} ({CLASSICAL_FROM})"
        return f"model {self.checkpoint} ({self.checkpoint_from})"


@dataclass
class Plan:
    """What one call does: the runs to evaluate and those skipped, each with its reason."""

    candidates: list[Candidate] = field(default_factory=list)
    skipped: list[dict[str, str]] = field(default_factory=list)


# --------------------------------------------------------------------------- inputs


def check_name(name: str | None, root: Path) -> str:
    """The metric prefix: ``name``, else the data root's folder name; letters, digits, ``_.-``."""
    text = root.name if name in (None, "") else str(name)
    if not NAME_PATTERN.match(text):
        raise ConfigError("name", text, "a prefix for the metrics: letters, digits, '_', '.', '-' (no '/')")
    return text


def check_root(root: str | None) -> tuple[Path, str]:
    """The other data root and its manifest's ``params_hash`` (``"none"`` without a manifest).

    A missing folder, or one without a test benchmark (``benchmarks/3DMatch|3DLoMatch``), is a DataError.
    """
    if root in (None, ""):
        raise ConfigError("data.root", root, "the data set to evaluate on, in the 3DMatch layout (data.root=DIR)")
    path = Path(str(root))
    if not path.is_dir():
        raise DataError(path, "data root (data.root) does not exist")
    layout = Layout(path)
    if not any(layout.benchmark_dir(b).is_dir() for b in BENCHMARKS):
        raise DataError(path / "benchmarks", f"holds no test benchmark ({' | '.join(BENCHMARKS)}): data.root is not "
                                             "a data set in the 3DMatch layout (python -m pcrcg.prepare makes one)")
    manifest = path / "manifest.json"
    params_hash = "none"
    if manifest.is_file():
        try:
            params_hash = str(json.loads(manifest.read_text()).get("params_hash") or "none")
        except (json.JSONDecodeError, AttributeError) as e:
            raise DataError(manifest, f"is not a manifest ({type(e).__name__}: {e})") from None
    return path, params_hash


def open_store(uri: str):
    """An MlflowClient on an existing store: a SQLite file that does not exist is a DataError (it
    would be created empty)."""
    from pcrcg.tracking.store import client, sqlite_path

    db = sqlite_path(uri)
    if db is not None and str(db) != ":memory:" and not db.is_file():
        raise DataError(db, "MLflow store does not exist (logger.tracking_uri, $MLFLOW_TRACKING_URI or "
                            "sqlite:///mlflow.db in this folder)")
    return client(uri)


def experiment_ids(mlflow_client: Any, names: Sequence[str], uri: str) -> dict[str, str]:
    """``{name: experiment id}``; an empty list or a name the store lacks is a ConfigError naming it."""
    if not names:
        raise ConfigError("experiments", list(names), "one or more MLflow experiment names "
                                                      "(experiments=[main_results,window_size])")
    out = {}
    for name in names:
        exp = mlflow_client.get_experiment_by_name(str(name))
        if exp is None or exp.lifecycle_stage == "deleted":
            have = sorted(e.name for e in mlflow_client.search_experiments())
            raise ConfigError("experiments", str(name), f"an experiment of the store {uri}: {', '.join(have) or 'none'}")
        out[str(name)] = exp.experiment_id
    return out


def finished_runs(mlflow_client: Any, exp_id: str) -> list[Any]:
    """Every FINISHED run of an experiment, oldest first (all pages)."""
    runs, token = [], None
    while True:
        page = mlflow_client.search_runs([exp_id], filter_string="attributes.status = 'FINISHED'",
                                         max_results=1000, order_by=["attributes.start_time ASC"], page_token=token)
        runs += list(page)
        token = getattr(page, "token", None)
        if not token:
            return runs


# --------------------------------------------------------------------------- what a run logged


def local_artifact(artifact_uri: str, rel: str) -> Path | None:
    """The local path of artifact ``rel`` of a run whose artifacts live in a local folder
    (``file://`` or a bare path), else None (a remote store: download it)."""
    parsed = urlparse(artifact_uri)
    if parsed.scheme == "file":
        return Path(unquote(parsed.path)) / rel
    if parsed.scheme == "" or re.match(r"^[A-Za-z]$", parsed.scheme or ""):  # a bare path (or a drive letter)
        return Path(artifact_uri) / rel
    return None


def fetch_artifact(mlflow_client: Any, run: Any, rel: str, tmp: Path) -> Path | None:
    """Artifact ``rel`` of ``run`` as a local file (the store's own file, or a download under ``tmp``);
    None when the run has no such artifact."""
    local = local_artifact(run.info.artifact_uri, rel)
    if local is not None:
        return local if local.is_file() else None
    try:
        dst = tmp / run.info.run_id
        dst.mkdir(parents=True, exist_ok=True)
        path = Path(mlflow_client.download_artifacts(run.info.run_id, rel, str(dst)))
    except Exception:  # noqa: BLE001 - MLflow raises several types for "no such artifact"
        return None
    return path if path.is_file() else None


def parse_param(text: str) -> Any:
    """A param value as :func:`pcrcg.tracking.hashing.flatten` wrote it, back to a plain value."""
    if text == "null":
        return None
    if text in ("True", "False"):
        return text == "True"
    if text[:1] in "[{":
        try:
            return json.loads(text)
        except json.JSONDecodeError:
            return text
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def unflatten(params: Mapping[str, str]) -> dict[str, Any]:
    """``{"a.b": "1"}`` -> ``{"a": {"b": 1}}`` (``protocol.*``, logged after evaluation, left out)."""
    out: dict[str, Any] = {}
    for key, text in sorted(params.items()):
        if key.startswith("protocol."):
            continue
        node = out
        *parents, leaf = key.split(".")
        for p in parents:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                break
            node = nxt
        else:
            node[leaf] = parse_param(text)
    return out


def run_config(mlflow_client: Any, run: Any, tmp: Path) -> tuple[dict[str, Any] | None, str]:
    """The run's resolved config: its ``config/config.yaml`` artifact (what the run wrote from its
    composed config), else its params (the same config flattened, values as text); ``(None, why)``
    when it logged neither."""
    import yaml

    path = fetch_artifact(mlflow_client, run, CONFIG_ARTIFACT, tmp)
    if path is not None:
        try:
            data = yaml.safe_load(path.read_text())
        except yaml.YAMLError as e:
            raise DataError(path, f"config of run {run.info.run_id} is not YAML ({type(e).__name__})") from None
        if isinstance(data, dict):
            return data, CONFIG_ARTIFACT
    if run.data.params.get("method") is not None:
        return unflatten(run.data.params), "params"
    return None, f"run logged neither {CONFIG_ARTIFACT} nor its config as params"


def trains_model(config: Mapping[str, Any]) -> bool:
    """Whether the run trained a model: ``method=learned``, or ICP started from the learned model."""
    method = config.get("method")
    return method == "learned" or (method in ("icp", "color_icp") and config.get("icp_init") == "learned")


def has_results(run: Any, name: str) -> bool:
    """Whether the run already holds metrics under ``<name>/``."""
    return any(k.startswith(f"{name}/") for k in run.data.metrics)


def _source_run(cache_dir: Path) -> str | None:
    """The run id ``source.json`` names beside a cached ``model.ckpt`` (None if unreadable)."""
    try:
        return json.loads((cache_dir / SOURCE_FILE).read_text()).get("run_id")
    except (OSError, json.JSONDecodeError, AttributeError):
        return None


def _cache_dir(config: Mapping[str, Any], base_dir: Path) -> Path:
    folder = Path(str((config.get("paths") or {}).get("checkpoints") or "checkpoints"))
    return folder if folder.is_absolute() else base_dir / folder


def find_checkpoint(mlflow_client: Any, run: Any, config: Mapping[str, Any], base_dir: Path,
                    tmp: Path) -> tuple[Path | None, str]:
    """The model file the run evaluated and where it was found (see the module docstring for the
    order); ``(None, what was looked at)`` when it is gone."""
    run_id = run.info.run_id
    looked = []
    path = fetch_artifact(mlflow_client, run, CHECKPOINT_ARTIFACT, tmp)
    if path is not None:
        return path, f"artifact {CHECKPOINT_ARTIFACT}"
    looked.append(f"artifact {CHECKPOINT_ARTIFACT}")
    trained_by = run.data.tags.get(TAG_REUSED_RUN)
    if trained_by and trained_by != "unknown":
        try:
            source = mlflow_client.get_run(trained_by)
        except Exception:  # noqa: BLE001 - a deleted run or another store
            source = None
        if source is not None:
            path = fetch_artifact(mlflow_client, source, CHECKPOINT_ARTIFACT, tmp)
            if path is not None:
                return path, f"artifact {CHECKPOINT_ARTIFACT} of run {trained_by} (tag {TAG_REUSED_RUN})"
        looked.append(f"the artifact of run {trained_by}")
        reused = run.data.tags.get(TAG_REUSED)
        if reused:
            cached = Path(reused)
            if cached.is_file() and _source_run(cached.parent) == trained_by:
                return cached, f"tag {TAG_REUSED} ({SOURCE_FILE} names run {trained_by})"
            looked.append(f"{cached} (tag {TAG_REUSED})")
    cache = _cache_dir(config, base_dir)
    if cache.is_dir():
        for d in sorted(p for p in cache.iterdir() if p.is_dir()):
            if (d / "model.ckpt").is_file() and _source_run(d) == run_id:
                return d / "model.ckpt", f"{d / SOURCE_FILE} names this run"
    looked.append(f"{cache}/*/{SOURCE_FILE}")
    return None, "checkpoint not found (looked at: " + "; ".join(looked) + ")"


def retrain_hint(run: Any) -> str:
    """For a run whose checkpoint is gone (a machine that kept the store and lost ``checkpoints/``): the
    command that trains the same config again into a new run of the same experiment (the tables count
    a seed's newest run), from the run's ``overrides`` tag; empty when the run has none."""
    overrides = (run.data.tags or {}).get("overrides", "").strip()
    if not overrides:
        return ""
    return (f"; to train it again into a new run of the same config (the report counts the newest): "
            f"python -m pcrcg.run {overrides} logger.skip_finished=false")


def model_views(checkpoint: Path) -> int:
    """Views per fragment the model lifts color from (0: geometry only); the file is read with
    :func:`pcrcg.models.train.read_checkpoint` first (no code runs; a corrupt file is a DataError)."""
    from pcrcg.errors import PcrcgError
    from pcrcg.models.train import load_module, read_checkpoint

    read_checkpoint(checkpoint)
    try:
        module = load_module(checkpoint, device="cpu")
    except PcrcgError:
        raise
    except Exception as e:  # noqa: BLE001 - a state dict that does not fit its hyper_parameters, on one line
        raise DataError(checkpoint, f"is not a usable checkpoint of `python -m pcrcg.run` ({type(e).__name__}: "
                                    f"{' '.join(str(e).split())[:200]})") from None
    n = int(module.lifter.cfg.n_views_needed) if module.lifter is not None else 0
    del module
    return n


def run_benchmarks(config: Mapping[str, Any]) -> list[str]:
    return list((config.get("eval") or {}).get("benchmarks") or BENCHMARKS)


def rebuilt_config(config: Mapping[str, Any], root: Path):
    """The run's config for the other root: ``data.root`` replaced, ``eval.max_pairs`` null (every pair)."""
    from omegaconf import OmegaConf

    data = json.loads(json.dumps(config))  # a deep copy of plain values
    data.setdefault("data", {})["root"] = str(root)
    data.setdefault("eval", {})["max_pairs"] = None
    return OmegaConf.create(data)


# --------------------------------------------------------------------------- plan, evaluate, log


def plan(mlflow_client: Any, experiments: Mapping[str, str], *, name: str, root: Path, base_dir: Path, tmp: Path,
         force: bool = False, run_ids: Iterable[str] = (), log: Callable[[str], None] = print) -> Plan:
    """Which runs to evaluate (config, checkpoint, views checked) and which to skip, with reasons.

    Raises before any evaluation: a corrupt checkpoint (DataError naming it), a run id of ``run_ids``
    not among the experiments' FINISHED runs, a benchmark or view file of ``root`` a run needs.
    """
    from pcrcg.evaluation.stage import check_layout, check_views

    wanted = set(run_ids)
    out = Plan()
    seen: set[str] = set()
    gts_cache: dict[tuple[str, ...], Any] = {}
    for exp_name, exp_id in experiments.items():
        for run in finished_runs(mlflow_client, exp_id):
            rid, rname = run.info.run_id, run.info.run_name or ""
            if wanted and rid not in wanted:
                continue
            seen.add(rid)

            def skip(reason: str) -> None:
                out.skipped.append({"run_id": rid, "experiment": exp_name, "run_name": rname, "reason": reason})
                log(f"[evaluate] skip run {rid} ({exp_name}: {rname}): {reason}")

            if has_results(run, name) and not force:
                skip(f"already has metrics under {name}/ (force=true evaluates it again)")
                continue
            config, source = run_config(mlflow_client, run, tmp)
            if config is None:
                skip(source)
                continue
            method = str(config.get("method"))
            if trains_model(config):
                ckpt, found = find_checkpoint(mlflow_client, run, config, base_dir, tmp)
                if ckpt is None:
                    skip(found + retrain_hint(run))
                    continue
                n_views = model_views(ckpt)
            elif method in CLASSICAL:  # no model: the method runs again; SIFT reads the views
                ckpt, found = None, CLASSICAL_FROM
                n_views = int(config.get("views") or 0) if method.startswith("sift") else 0
            else:
                skip(f"no trained model and no classical method (method={method}, icp_init={config.get('icp_init')})")
                continue
            key = tuple(run_benchmarks(config))
            if key not in gts_cache:
                gts_cache[key] = check_layout(root, key)
            check_views(root, gts_cache[key], n_views)
            out.candidates.append(Candidate(rid, exp_name, rname, config, ckpt, found, n_views))
    missing = sorted(wanted - seen)
    if missing:
        raise ConfigError("run_ids", missing[0], "ids of FINISHED runs of the experiments "
                                                 f"{', '.join(experiments)}")
    return out


def prefixed(metrics: Mapping[str, float], name: str) -> dict[str, float]:
    """``{"3DMatch/rr_5000": v}`` -> ``{"<name>/3DMatch/rr_5000": v}`` (None values left out)."""
    return {f"{name}/{k}": float(v) for k, v in metrics.items() if v is not None}


def evaluate_candidate(tracker: Any, cand: Candidate, *, name: str, root: Path, params_hash: str,
                       progress: bool = True) -> dict[str, float]:
    """Evaluate one run's model on ``root`` as its evaluation stage did and log into the run
    (artifacts and tags first, metrics last). Returns the prefixed metrics."""
    from pcrcg.evaluation.stage import evaluate
    from pcrcg.device import resolve_device
    from pcrcg.tracking.git import code_version

    cfg = rebuilt_config(cand.config, root)
    device = resolve_device((cand.config.get("runtime") or {}).get("device"))
    with tempfile.TemporaryDirectory(prefix="pcrcg-tracked-") as tmp:
        result = evaluate(cfg, data_root=root, checkpoint=cand.checkpoint, out_dir=Path(tmp) / "eval",
                          device=device, progress=progress)
        for path, folder in result["artifacts"]:
            tracker.log_artifact(cand.run_id, path, f"{name}/{folder}" if folder else name)
    model = CLASSICAL_FROM if cand.checkpoint is None else f"{cand.checkpoint} ({cand.checkpoint_from})"
    tracker.set_tags(cand.run_id, {f"{name}.data_root": f"{root.resolve()} params_hash={params_hash}",
                                   f"{name}.checkpoint": model,
                                   f"{name}.code_version": code_version()})
    metrics = prefixed(result["metrics"], name)
    tracker.log_metrics(cand.run_id, metrics)
    return metrics


def run_tracked(cfg: Any, base_dir: Path | None = None, log: Callable[[str], None] = print) -> dict[str, Any]:
    """``python -m pcrcg.evaluate mode=tracked``: see the module docstring. Returns the JSON-ready
    summary ``{"mode", "name", "data_root", "params_hash", "tracking_uri", "experiments", "evaluated":
    [{run_id, experiment, run_name, checkpoint, seconds, metrics}], "skipped": [{..., reason}], "failed": [...]}``."""
    from omegaconf import OmegaConf

    from pcrcg.cli import strict_json
    from pcrcg.tracking.tracker import RunTracker
    from pcrcg.tracking.store import resolve_tracking_uri

    base = Path(base_dir) if base_dir is not None else Path.cwd()
    root, params_hash = check_root(OmegaConf.select(cfg, "data.root"))
    name = check_name(OmegaConf.select(cfg, "name"), root)
    uri = resolve_tracking_uri(OmegaConf.select(cfg, "logger.tracking_uri"), base)
    mlflow_client = open_store(uri)
    names = [str(n) for n in (OmegaConf.select(cfg, "experiments") or [])]
    exps = experiment_ids(mlflow_client, names, uri)
    force = bool(OmegaConf.select(cfg, "force", default=False))
    run_ids = [str(r) for r in (OmegaConf.select(cfg, "run_ids") or [])]
    summary: dict[str, Any] = {"mode": "tracked", "name": name, "data_root": str(root), "params_hash": params_hash,
                               "tracking_uri": uri, "experiments": names, "evaluated": [], "skipped": [], "failed": []}
    with tempfile.TemporaryDirectory(prefix="pcrcg-tracked-artifacts-") as tmp:
        todo = plan(mlflow_client, exps, name=name, root=root, base_dir=base, tmp=Path(tmp), force=force,
                    run_ids=run_ids, log=log)
        summary["skipped"] = todo.skipped
        log(f"[evaluate] {len(todo.candidates)} run(s) to evaluate on {root} as {name}/, {len(todo.skipped)} skipped")
        trackers: dict[str, RunTracker] = {}
        for k, cand in enumerate(todo.candidates, 1):
            log(f"[evaluate] run {k}/{len(todo.candidates)}: {cand.run_id} ({cand.experiment}: {cand.run_name}), "
                f"{cand.model}")
            t0 = time.perf_counter()
            tracker = trackers.setdefault(cand.experiment, RunTracker(uri, cand.experiment))
            try:
                metrics = evaluate_candidate(tracker, cand, name=name, root=root, params_hash=params_hash,
                                             progress=bool(OmegaConf.select(cfg, "progress", default=True)))
            except Exception as e:  # noqa: BLE001 - one run's failure does not stop the others
                text = " ".join(str(e).split())[:300] or type(e).__name__
                summary["failed"].append({"run_id": cand.run_id, "experiment": cand.experiment,
                                          "run_name": cand.run_name, "error": f"{type(e).__name__}: {text}"})
                log(f"[evaluate] failed run {cand.run_id}: {type(e).__name__}: {text} (the next call retries it)")
                continue
            seconds = round(time.perf_counter() - t0, 1)
            shown = {k2: v for k2, v in metrics.items() if SHOWN.search(k2)}
            head = (f"/rr_{max_n(cand.config)}", "/rr")  # the headline recall: a learned model's at its largest N, ICP's
            rr = ", ".join(f"{k2.split('/', 1)[1]}={v:.1f}" for k2, v in shown.items() if k2.endswith(head))
            log(f"[evaluate] done run {cand.run_id} in {seconds} s: {rr or 'logged'}")
            summary["evaluated"].append({"run_id": cand.run_id, "experiment": cand.experiment,
                                         "run_name": cand.run_name,
                                         "checkpoint": None if cand.checkpoint is None else str(cand.checkpoint),
                                         "checkpoint_from": cand.checkpoint_from, "seconds": seconds,
                                         "metrics": json.loads(strict_json(shown))})
    return summary


def max_n(config: Mapping[str, Any]) -> int:
    """The largest N of the run's evaluation (its headline recall)."""
    ns = (config.get("eval") or {}).get("n_points") or [5000]
    return max(int(n) for n in ns)
