"""Hydra callback of ``python -m pcrcg.run -m``: set up before the jobs, sum up after them.

``on_multirun_start`` (parent process, before any job):
  * checks every value the sweep will take (``hydra.sweeper.params`` and command-line sweeps), then
    composes and validates every job's config as the job will (a sweep value of any key, like
    ``trainer.optim.lr=0.1,abc``, fails here, naming the job, before the first job starts);
  * creates the MLflow store and the experiment once (parallel jobs that open a brand-new
    SQLite store at once race in its schema migration);
  * prepares the data set once when all jobs share it (jobs would otherwise build it twice).

``on_multirun_end`` (parent): prints what each job did (from the ``pcrcg_status.json`` files
the jobs leave in their folders), writes the experiment's tables (``runtime.report_on_end``),
prints where they are and how to open the MLflow UI, and fails the command when a job failed.

Hydra turns exceptions raised by callbacks into warnings; the callback ends the command with
``SystemExit`` instead (exit code 2: a bad sweep value, 1: a failure).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from pcrcg.pipeline import STATUS_FILE

# sweep keys that change the data set: the parent cannot prepare it once for all jobs
_DATA_KEYS = ("data", "profile", "data_seed", "paths")


def _sweep_overrides(config: DictConfig) -> tuple[list[str], dict[str, Any]]:
    """The command line's task overrides and the sweeper's ``params`` (``{}`` when there are none:
    a plain command-line sweep without an experiment file)."""
    task = [str(o) for o in config.hydra.overrides.task]
    node = config.hydra.sweeper.get("params")
    params = OmegaConf.to_container(node, resolve=False) if isinstance(node, DictConfig) else dict(node or {})
    assert isinstance(params, dict)
    return task, {str(k): v for k, v in params.items()}


def _job_overrides(config: DictConfig, task: list[str], params: dict[str, Any]) -> list[list[str]] | None:
    """Every job's overrides, as Hydra's basic sweeper will make them (None for other sweepers)."""
    target = str(OmegaConf.select(config, "hydra.sweeper._target_", default=""))
    if not target.endswith("BasicSweeper"):
        return None
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides([*(f"{k}={v}" for k, v in params.items()), *task])
    return [list(job) for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


def _validate_jobs(config: DictConfig, jobs: list[list[str]], dirs: tuple[Path, ...]) -> None:
    """Compose each job's config as the launcher will and validate it (ConfigError on the first bad one)."""
    from hydra.core.global_hydra import GlobalHydra

    from pcrcg.config import validate_run_config
    from pcrcg.errors import ConfigError

    loader = GlobalHydra.instance().hydra.config_loader  # type: ignore[union-attr]
    values: dict[str, set[str]] = {}
    for job in jobs:
        for o in job:
            values.setdefault(o.split("=", 1)[0], set()).add(o)
    swept = {k for k, v in values.items() if len(v) > 1}

    def name(job: list[str]) -> str:  # what differs between the jobs (window_size=7), else everything
        return " ".join(o for o in job if o.split("=", 1)[0] in swept) or " ".join(job) or "defaults"

    for job in jobs:
        try:
            cfg = loader.load_sweep_config(config, job)
        except Exception as e:  # noqa: BLE001 - Hydra's own composition errors (a key that does not exist)
            raise ConfigError(name(job), "(composition)", f"a valid override ({' '.join(str(e).split())})") from None
        choices = {k: v for k, v in cfg.hydra.runtime.choices.items() if v is not None}
        body = OmegaConf.masked_copy(cfg, [k for k in cfg.keys() if k != "hydra"])
        try:
            validate_run_config(body, choices, dirs)
        except ConfigError as e:
            e.args = (f"{e} (job {name(job)})",)
            raise


def _base_dir(config: DictConfig) -> Path:
    try:
        return Path(HydraConfig.get().runtime.cwd)
    except Exception:  # noqa: BLE001 - no Hydra context (direct call)
        return Path.cwd()


def _search_dirs(config: DictConfig) -> tuple[Path, ...]:
    from pcrcg.config import CONF_DIR

    dirs = [Path(s.path) for s in config.hydra.runtime.config_sources if s.schema == "file"]
    return tuple(dirs) or (CONF_DIR,)


def _stop(message: str, code: int) -> None:
    """End the command now. Hydra turns a callback's exceptions into warnings and goes on;
    ``SystemExit`` is not an ``Exception``, so it does stop the sweep (before any job here)."""
    print(message, file=sys.stderr)
    raise SystemExit(code)


class TrackingCallback(Callback):
    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from pcrcg.config import check_overrides, check_sweep_params
        from pcrcg.errors import ConfigError

        self._started = time.time()
        task, params = _sweep_overrides(config)
        dirs = _search_dirs(config)
        try:
            check_overrides([o for o in task if not o.startswith("hydra")], dirs)
            check_sweep_params(params, dirs)
            jobs = _job_overrides(config, task, params)
            if jobs is not None:
                _validate_jobs(config, jobs, dirs)
        except ConfigError as e:
            _stop(f"pcrcg.run: {e} (in the sweep; no job was started)", 2)
        base = _base_dir(config)
        if config.logger.name == "mlflow":
            from pcrcg.tracking.store import client, ensure_experiment, ensure_store, resolve_tracking_uri

            uri = resolve_tracking_uri(config.logger.tracking_uri, base)
            try:
                ensure_store(uri)
                ensure_experiment(client(uri), str(config.experiment_name), uri)
            except Exception as e:  # noqa: BLE001
                _stop(f"pcrcg.run: cannot open the MLflow store {uri}: {type(e).__name__}: {e}", 1)
        try:
            self._prepare_once(config, task, params, base)
        except ConfigError as e:
            _stop(f"pcrcg.run: {e} (preparing the data set; no job was started)", 2)
        except Exception as e:  # noqa: BLE001
            _stop(f"pcrcg.run: preparing the data set failed: {type(e).__name__}: {e}", 1)

    def _prepare_once(self, config: DictConfig, task: list[str], params: dict[str, Any], base: Path) -> None:
        swept = {k.lstrip("+~").split(".")[0] for k in params}
        swept |= {o.split("=", 1)[0].lstrip("+~").split(".")[0] for o in task if "," in o.split("=", 1)[-1]}
        if swept & set(_DATA_KEYS):
            print("[run] the sweep changes the data set: each job prepares its own")
            return
        from hydra.utils import get_method

        from pcrcg.pipeline import JobInfo, RunContext

        cfg = OmegaConf.masked_copy(config, [k for k in config.keys() if k != "hydra"])
        ctx = RunContext(cfg=cfg, job=JobInfo(output_dir=base, base_dir=base), out_dir=base, device="cpu")
        root = get_method(str(config.stages.prepare))(ctx)
        print(f"[run] data set ready for all jobs: {root}")

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        if not sweep_dir.is_absolute():
            sweep_dir = _base_dir(config) / sweep_dir
        started = getattr(self, "_started", 0.0) - 1.0  # only this sweep's jobs (a folder may be reused)
        files = sorted(sweep_dir.rglob(STATUS_FILE), key=lambda p: (len(p.parent.name), p.parent.name))
        statuses = [json.loads(p.read_text()) for p in files if p.stat().st_mtime >= started]
        counts: dict[str, int] = {}
        for s in statuses:
            counts[s["status"]] = counts.get(s["status"], 0) + 1
        print(f"[sweep] {config.experiment_name}: {len(statuses)} jobs: "
              + ", ".join(f"{n} {k}" for k, n in sorted(counts.items())))
        for s in statuses:
            line = f"[sweep]   {s['status']:<8} {s['run_name']:<40} run {s.get('run_id') or '-'}"
            if s.get("error"):
                line += f"  ({s['error'][:200]})"
            print(line)
        uri = next((s["tracking_uri"] for s in statuses if s.get("tracking_uri")), None)
        if config.runtime.get("report_on_end", False) and uri is not None:
            from pcrcg.report import write_experiment_tables

            write_experiment_tables(str(config.experiment_name), uri, OmegaConf.select(config, "profile.name"),
                                    str(config.runtime.get("report_dir", "reports")), _base_dir(config), "[sweep]")
        if uri is not None:
            from pcrcg.tracking.store import ui_command

            print(f"[sweep] MLflow: {ui_command(uri)}   (experiment {config.experiment_name!r})")
        failed = [s for s in statuses if s["status"] == "failed"]
        if failed:
            _stop(f"[sweep] {len(failed)} of {len(statuses)} jobs failed (recorded as FAILED in MLflow; "
                  f"relaunch the same command to run only what is missing)", 1)
