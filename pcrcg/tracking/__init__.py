"""MLflow tracking helpers: store URI, config hash, git sha, the run tracker (the multirun callback: :mod:`pcrcg.sweep`).

``mlflow`` itself is imported lazily (it costs about 2 s), so importing this package is cheap.
"""

from pcrcg.tracking.git import git_info
from pcrcg.tracking.hashing import HASH_EXCLUDE, TRAIN_HASH_EXCLUDE, config_hash, flat_params, flatten
from pcrcg.tracking.store import ensure_experiment, ensure_store, resolve_tracking_uri, ui_command

__all__ = [
    "HASH_EXCLUDE",
    "TRAIN_HASH_EXCLUDE",
    "config_hash",
    "ensure_experiment",
    "ensure_store",
    "flat_params",
    "flatten",
    "git_info",
    "resolve_tracking_uri",
    "ui_command",
]
