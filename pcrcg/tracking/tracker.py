"""The run tracker (one tracked run in MLflow): find a finished twin, start, log, finish or record a failure.

Everything goes through an explicit ``MlflowClient`` bound to one store URI (no global
``mlflow`` state), so parallel jobs and several stores in one process do not interfere.

Every run records the process that owns it (tags ``pcrcg.host``, ``pcrcg.pid``, ``pcrcg.pid_start``:
the process's start time, so that a reused pid is not taken for the owner) and the machine that computes it
(``pcrcg.cpu``, ``pcrcg.cpu_capability``, ``pcrcg.cuda``: :func:`machine_tags`). A run left RUNNING by a
process that is gone (SIGKILL, a power cut) is *stale*: :meth:`RunTracker.close_stale` ends such runs
of a config hash as KILLED before the config runs again, and the report leaves them out
(:func:`is_stale`). Runs owned by another host are never judged stale from here.
"""

from __future__ import annotations

import math
import os
import socket
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from pcrcg.tracking.git import code_version, git_info
from pcrcg.tracking.store import client, ensure_experiment, ensure_store

# MLflow's per-request limits (log_batch) and its longest param value
_MAX_PARAMS = 100
_MAX_METRICS = 1000
_MAX_TAGS = 100
MAX_PARAM_LEN = 6000
_MAX_TAG_LEN = 5000

# tags every run carries
TAG_EXPERIMENT = "experiment"
TAG_HASH = "config_hash"
TAG_GIT = "git_sha"
TAG_CODE = "code_version"
TAG_PROFILE = "profile"
TAG_ERROR = "error"
TAG_ERROR_TYPE = "error_type"
TAG_NOT_RUN = "not_run"
TAG_HOST = "pcrcg.host"
TAG_PID = "pcrcg.pid"
TAG_PID_START = "pcrcg.pid_start"
TAG_CPU = "pcrcg.cpu"
TAG_CPU_CAPABILITY = "pcrcg.cpu_capability"
TAG_CUDA = "pcrcg.cuda"
TAG_CLOSED_STALE = "closed_stale"


def process_start(pid: int) -> str | None:
    """When process ``pid`` started (clock ticks since boot, from /proc), or None where unknown."""
    try:
        stat = Path(f"/proc/{int(pid)}/stat").read_text()
    except (OSError, ValueError):
        return None
    # the command name (field 2) may hold spaces and parentheses: count fields after the last ')'
    return stat.rsplit(")", 1)[-1].split()[19]


def identity_tags(experiment: str, config_hash: str, profile: str) -> dict[str, str]:
    """The tags that say what a tracked run is and which code made it, for every kind of run (a run of
    :mod:`pcrcg.pipeline`, a 2D pretraining): its experiment, config hash and profile, the git commit
    (also as MLflow's own ``mlflow.source.git.commit``), whether the checkout was dirty, and the
    :func:`~pcrcg.tracking.git.code_version`."""
    sha, dirty = git_info()
    return {TAG_EXPERIMENT: experiment, TAG_HASH: config_hash, TAG_GIT: sha, "git_dirty": str(dirty).lower(),
            TAG_CODE: code_version(), TAG_PROFILE: profile, "mlflow.source.git.commit": sha}


def owner_tags() -> dict[str, str]:
    """Tags naming this process as a run's owner."""
    pid = os.getpid()
    return {TAG_HOST: socket.gethostname(), TAG_PID: str(pid), TAG_PID_START: process_start(pid) or ""}


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; elsewhere :func:`platform.processor` or the architecture)."""
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text(errors="replace").splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def machine_tags() -> dict[str, str]:
    """Tags naming the machine that computes a run: its CPU model, the instruction set torch's CPU kernels
    dispatch to (``AVX512``, ``AVX2``, ...) and the CUDA device, if any. Runs of one config, code and seed
    differ between CPU types (Predator seed 0 at the cpu profile: 3DLoMatch 35.07% on an AMD EPYC, 30.04% on an
    Intel Xeon; equal to every digit on two Intel machines): a sweep of record should come from one kind."""
    import torch

    tags = {TAG_CPU: cpu_model(), TAG_CPU_CAPABILITY: str(torch.backends.cpu.get_cpu_capability())}
    if torch.cuda.is_available():
        tags[TAG_CUDA] = torch.cuda.get_device_name(0)
    return tags


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def is_stale(status: str, tags: Mapping[str, Any]) -> bool:
    """A RUNNING run whose owning process (on this host) is gone."""
    if status != "RUNNING":
        return False
    host, pid = tags.get(TAG_HOST), tags.get(TAG_PID)
    if not host or not pid or host != socket.gethostname():
        return False
    try:
        pid_i = int(pid)
    except (TypeError, ValueError):
        return False
    if not _pid_alive(pid_i):
        return True
    started = tags.get(TAG_PID_START) or ""
    now = process_start(pid_i)
    return bool(started and now and started != now)  # the pid now belongs to another process


@dataclass(frozen=True)
class FinishedRun:
    run_id: str
    run_name: str
    config_hash: str


class RunTracker:
    """Runs of one MLflow experiment in the store at ``uri``."""

    def __init__(self, uri: str, experiment_name: str):
        self.uri = uri
        self.experiment_name = experiment_name
        ensure_store(uri)
        self.client = client(uri)
        self.experiment_id = ensure_experiment(self.client, experiment_name, uri)

    # ------------------------------------------------------------------ lookup
    def find_finished(self, config_hash: str, code_version: str | None = None) -> FinishedRun | None:
        """The newest FINISHED run of this experiment whose ``config_hash`` tag is ``config_hash`` (and, when
        given, whose ``code_version`` tag is ``code_version``)."""
        code = f" and tags.{TAG_CODE} = '{code_version}'" if code_version is not None else ""
        runs = self.client.search_runs(
            [self.experiment_id],
            filter_string=f"tags.{TAG_HASH} = '{config_hash}' and attributes.status = 'FINISHED'{code}",
            max_results=1,
            order_by=["attributes.start_time DESC"],
        )
        if not runs:
            return None
        r = runs[0]
        return FinishedRun(r.info.run_id, r.info.run_name or "", config_hash)

    def find_finished_named(self, run_name: str, code_version: str | None = None) -> FinishedRun | None:
        """The newest FINISHED run of this experiment named ``run_name`` (the same job's overrides), whatever
        its config hash (and, when given, whose ``code_version`` tag is ``code_version``)."""
        code = f" and tags.{TAG_CODE} = '{code_version}'" if code_version is not None else ""
        runs = self.client.search_runs([self.experiment_id], filter_string=f"attributes.status = 'FINISHED'{code}",
                                       max_results=5000, order_by=["attributes.start_time DESC"])
        for r in runs:
            if (r.info.run_name or "") == run_name:
                return FinishedRun(r.info.run_id, run_name, r.data.tags.get(TAG_HASH, ""))
        return None

    def params(self, run_id: str) -> dict[str, str]:
        """The run's logged params (``{"a.b": "value"}``)."""
        return dict(self.client.get_run(run_id).data.params)

    # ------------------------------------------------------------------ life cycle
    def start(self, run_name: str, tags: Mapping[str, str]) -> str:
        run = self.client.create_run(self.experiment_id, run_name=run_name,
                                     tags={**owner_tags(), **machine_tags(), **dict(tags)})
        return run.info.run_id

    def close_stale(self, config_hash: str) -> list[str]:
        """End as KILLED the RUNNING runs of ``config_hash`` whose process is gone; their ids."""
        runs = self.client.search_runs(
            [self.experiment_id],
            filter_string=f"tags.{TAG_HASH} = '{config_hash}' and attributes.status = 'RUNNING'",
            max_results=100,
        )
        closed = []
        for r in runs:
            if is_stale(r.info.status, r.data.tags):
                self.set_tags(r.info.run_id, {TAG_CLOSED_STALE: "true", TAG_ERROR_TYPE: "Killed",
                                              TAG_ERROR: f"process {r.data.tags.get(TAG_PID)} ended without "
                                                         "closing the run (killed?); closed by a relaunch"})
                self.client.set_terminated(r.info.run_id, "KILLED")
                closed.append(r.info.run_id)
        return closed

    def kill(self, run_id: str, reason: str) -> None:
        """End the run as KILLED (Ctrl-C, SIGTERM), saying why."""
        try:
            self.set_tags(run_id, {TAG_ERROR_TYPE: "Interrupted", TAG_ERROR: reason})
        finally:
            self.client.set_terminated(run_id, "KILLED")

    def finish(self, run_id: str) -> None:
        self.client.set_terminated(run_id, "FINISHED")

    def fail(self, run_id: str, error: BaseException, not_run: bool = False) -> None:
        """Record ``error`` (type, message, traceback artifact ``error.txt``) and end the run as FAILED.

        ``not_run``: the run never started its work for a reason the user must fix
        (e.g. a weights file that is not configured); the report shows the reason.
        """
        tags = {TAG_ERROR_TYPE: type(error).__name__, TAG_ERROR: str(error)[:_MAX_TAG_LEN] or type(error).__name__}
        if not_run:
            tags[TAG_NOT_RUN] = "true"
        try:
            self.set_tags(run_id, tags)
            text = "".join(traceback.format_exception(type(error), error, error.__traceback__))
            self.log_text(run_id, text, "error.txt")
        finally:
            self.client.set_terminated(run_id, "FAILED")

    # ------------------------------------------------------------------ logging
    def set_tags(self, run_id: str, tags: Mapping[str, Any]) -> None:
        from mlflow.entities import RunTag

        items = [RunTag(k, str(v)[:_MAX_TAG_LEN]) for k, v in tags.items()]
        for i in range(0, len(items), _MAX_TAGS):
            self.client.log_batch(run_id, tags=items[i:i + _MAX_TAGS])

    def log_params(self, run_id: str, params: Mapping[str, Any]) -> None:
        from mlflow.entities import Param

        items = [Param(k, str(v)[:MAX_PARAM_LEN]) for k, v in params.items()]
        for i in range(0, len(items), _MAX_PARAMS):
            self.client.log_batch(run_id, params=items[i:i + _MAX_PARAMS])

    def log_metrics(self, run_id: str, metrics: Mapping[str, float], step: int = 0) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, step) for k, v in metrics.items() if v is not None]
        for i in range(0, len(items), _MAX_METRICS):
            self.client.log_batch(run_id, metrics=items[i:i + _MAX_METRICS])

    def log_history(self, run_id: str, history: Mapping[str, Any]) -> None:
        """Training curves: ``{name: [v0, v1, ...]}`` (step = index) or ``[(step, v), ...]``."""
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = []
        for name, values in history.items():
            for k, v in enumerate(values):
                step, value = (v if isinstance(v, (tuple, list)) else (k, v))
                if value is not None and math.isfinite(float(value)):
                    items.append(Metric(name, float(value), now, int(step)))
        for i in range(0, len(items), _MAX_METRICS):
            self.client.log_batch(run_id, metrics=items[i:i + _MAX_METRICS])

    def log_artifact(self, run_id: str, path: str | os.PathLike, artifact_path: str | None = None) -> None:
        """Copy a file or a folder into the run's artifacts (under ``artifact_path``)."""
        path = Path(path)
        if path.is_dir():
            self.client.log_artifacts(run_id, str(path), artifact_path)
        elif path.is_file():
            self.client.log_artifact(run_id, str(path), artifact_path)

    def log_text(self, run_id: str, text: str, name: str) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            p = Path(tmp) / Path(name).name
            p.write_text(text)
            parent = str(Path(name).parent)
            self.client.log_artifact(run_id, str(p), None if parent == "." else parent)

    def artifact_uri(self, run_id: str) -> str:
        return self.client.get_run(run_id).info.artifact_uri
