"""One tracked run in MLflow: find a finished twin, start, log, finish or record a failure.

Everything goes through an explicit ``MlflowClient`` bound to one store URI (no global
``mlflow`` state), so parallel jobs and several stores in one process do not interfere.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from pcrcg.tracking.store import client, ensure_experiment

# MLflow's per-request limits (log_batch) and its longest param value
_MAX_PARAMS = 100
_MAX_METRICS = 1000
_MAX_TAGS = 100
_MAX_PARAM_LEN = 6000
_MAX_TAG_LEN = 5000

# tags every run carries
TAG_EXPERIMENT = "experiment"
TAG_HASH = "config_hash"
TAG_GIT = "git_sha"
TAG_PROFILE = "profile"
TAG_ERROR = "error"
TAG_ERROR_TYPE = "error_type"
TAG_NOT_RUN = "not_run"


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
        self.client = client(uri)
        self.experiment_id = ensure_experiment(self.client, experiment_name, uri)

    # ------------------------------------------------------------------ lookup
    def find_finished(self, config_hash: str) -> FinishedRun | None:
        """The newest FINISHED run of this experiment whose ``config_hash`` tag is ``config_hash``."""
        runs = self.client.search_runs(
            [self.experiment_id],
            filter_string=f"tags.{TAG_HASH} = '{config_hash}' and attributes.status = 'FINISHED'",
            max_results=1,
            order_by=["attributes.start_time DESC"],
        )
        if not runs:
            return None
        r = runs[0]
        return FinishedRun(r.info.run_id, r.info.run_name or "", config_hash)

    # ------------------------------------------------------------------ life cycle
    def start(self, run_name: str, tags: Mapping[str, str]) -> str:
        run = self.client.create_run(self.experiment_id, run_name=run_name, tags=dict(tags))
        return run.info.run_id

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

        items = [Param(k, str(v)[:_MAX_PARAM_LEN]) for k, v in params.items()]
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
