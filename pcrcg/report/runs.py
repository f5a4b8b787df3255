"""Read tracked runs from an MLflow store into a pandas DataFrame."""

from __future__ import annotations

from typing import Sequence

import pandas as pd

RUN_COLUMNS = ("run_id", "experiment_id", "status", "start_time", "end_time")


def load_runs(uri: str, experiments: Sequence[str]) -> pd.DataFrame:
    """All runs of the named experiments (those that exist), one row per run.

    Columns: ``run_id, experiment_id, status, start_time, end_time, experiment`` and MLflow's
    ``metrics.*``, ``params.*``, ``tags.*``.
    """
    import mlflow

    from pcrcg.tracking.store import client

    c = client(uri)
    ids = {}
    for name in dict.fromkeys(experiments):
        exp = c.get_experiment_by_name(name)
        if exp is not None and exp.lifecycle_stage == "active":
            ids[exp.experiment_id] = name
    if not ids:
        return pd.DataFrame(columns=[*RUN_COLUMNS, "experiment"])
    previous = mlflow.get_tracking_uri()
    mlflow.set_tracking_uri(uri)
    try:
        df = mlflow.search_runs(experiment_ids=list(ids), output_format="pandas", max_results=100000)
    finally:
        mlflow.set_tracking_uri(previous)
    if df.empty:
        return pd.DataFrame(columns=[*RUN_COLUMNS, "experiment"])
    df["experiment"] = df["experiment_id"].map(ids)
    return df.sort_values("start_time").reset_index(drop=True)


def newest_profile(runs: pd.DataFrame, experiment: str) -> str | None:
    """Profile of the newest FINISHED run of ``experiment`` (None if there is none)."""
    if "tags.profile" not in runs.columns:
        return None
    sel = runs[(runs["experiment"] == experiment) & (runs["status"] == "FINISHED")]
    if sel.empty:
        return None
    return str(sel.sort_values("start_time").iloc[-1]["tags.profile"])
