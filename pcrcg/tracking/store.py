"""Where runs are recorded: the MLflow store URI, its creation, and experiments in it.

Resolution order of the store URI: the configured ``logger.tracking_uri``, else the
environment variable ``MLFLOW_TRACKING_URI``, else ``sqlite:///<base_dir>/mlflow.db``
(``base_dir``: the folder the command was started from). A relative SQLite path is made
absolute against ``base_dir`` so that jobs started elsewhere (submitit, ray) share it.

A brand-new SQLite store must be created once, before parallel jobs open it: they race
in its schema migration otherwise (``duplicate column name: step``). :func:`ensure_store` does
that under a file lock (``<db>.lock``), so that separate commands started at once (``for w in 3 7; do
python -m pcrcg.run ... & done``) create it once too; the multirun callback calls it in the parent
process and every run calls it before its first query.

``mlflow`` is imported lazily: it costs about 2 s.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Mapping

if TYPE_CHECKING:  # pragma: no cover
    from mlflow.tracking import MlflowClient

ENV_URI = "MLFLOW_TRACKING_URI"
DEFAULT_DB = "mlflow.db"
ARTIFACT_DIR = "mlartifacts"
_SQLITE = "sqlite:///"


def resolve_tracking_uri(
    configured: str | None = None,
    base_dir: str | os.PathLike | None = None,
    env: Mapping[str, str] | None = None,
) -> str:
    """The store URI to use (see module docstring); relative SQLite paths made absolute."""
    env = os.environ if env is None else env
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    uri = configured or env.get(ENV_URI) or f"{_SQLITE}{DEFAULT_DB}"
    if uri.startswith(_SQLITE):
        path = uri[len(_SQLITE):]
        if path != ":memory:" and not path.startswith("/"):
            uri = f"{_SQLITE}{(base / path).resolve()}"
    elif "://" not in uri and not uri.startswith("databricks"):
        # a bare folder: MLflow's file store (needs MLFLOW_ALLOW_FILE_STORE in MLflow 3)
        uri = str((base / uri).resolve())
    return uri


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI, else None."""
    if uri.startswith(_SQLITE):
        return Path(uri[len(_SQLITE):])
    return None


def require_store(uri: str, hint: str = "--tracking-uri or MLFLOW_TRACKING_URI") -> None:
    """A SQLite store that is not there: a :class:`pcrcg.errors.PcrcgError` naming the file, before anything is
    read or written (nothing is created). ``hint``: how the command names its store."""
    from pcrcg.errors import PcrcgError

    db = sqlite_path(uri)
    if db is not None and str(db) != ":memory:" and not db.is_file():
        raise PcrcgError(f"{db}: no MLflow store there ({hint})")


def artifact_root(uri: str) -> str | None:
    """Where experiments created here keep their artifacts: ``mlartifacts/`` beside a SQLite
    file, the server's default (None) otherwise."""
    db = sqlite_path(uri)
    if db is None:
        return None
    return (db.parent / ARTIFACT_DIR).resolve().as_uri()


def ui_command(uri: str) -> str:
    """The command that opens the MLflow UI on this store."""
    if uri.startswith(("http://", "https://")):
        return f"open {uri} in a browser (the tracking server's UI)"
    return f"mlflow ui --backend-store-uri {uri}"


def client(uri: str) -> "MlflowClient":
    from mlflow.tracking import MlflowClient

    return MlflowClient(tracking_uri=uri)


_READY: set[str] = set()


def ensure_store(uri: str) -> None:
    """Create the store's schema now if it is a new SQLite file, under a file lock: one process
    creates it, the others wait and find it made."""
    if uri in _READY:
        return
    db = sqlite_path(uri)
    if db is None or str(db) == ":memory:":
        client(uri).search_experiments(max_results=1)
    else:
        from filelock import FileLock

        db.parent.mkdir(parents=True, exist_ok=True)
        with FileLock(str(db) + ".lock"):
            client(uri).search_experiments(max_results=1)
    _READY.add(uri)


def ensure_experiment(mlflow_client: "MlflowClient", name: str, uri: str, retries: int = 5) -> str:
    """Id of the experiment ``name``, created (or restored from deleted) if needed.

    Safe when several jobs call it at once: a creation race is retried by looking it up again.
    """
    from mlflow.exceptions import MlflowException

    for attempt in range(retries):
        exp = mlflow_client.get_experiment_by_name(name)
        if exp is not None:
            if exp.lifecycle_stage == "deleted":
                mlflow_client.restore_experiment(exp.experiment_id)
            return exp.experiment_id
        try:
            root = artifact_root(uri)
            location = f"{root}/{name}" if root else None
            return mlflow_client.create_experiment(name, artifact_location=location)
        except MlflowException:
            time.sleep(0.2 * (attempt + 1))
    exp = mlflow_client.get_experiment_by_name(name)
    if exp is None:
        raise RuntimeError(f"could not create MLflow experiment {name!r} in {uri}")
    return exp.experiment_id
