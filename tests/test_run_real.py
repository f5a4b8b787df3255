"""The real stages through the real entry point, at the tiny profile: two sweeps, the second reusing
the first's model.

Nothing is faked: ``python -m pcrcg.run ... -m`` (in-process) runs ``pipeline.prepare_data`` (the
session's tiny data set, found up to date by its manifest), ``pipeline.train_model`` (4 steps into
the checkpoint cache keyed by the training hash, under the cache's file lock, with ``source.json``)
and ``pipeline.evaluate_method`` (one pair per benchmark at N = 250). The second sweep, window_size
11, needs the model main_results trained for PCR-CG (11 is the default window): it must reuse it,
as the README says.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pcrcg.config import CONF_DIR
from test_run_support import read_status_files, run_cli, tracked_runs

# what both sweeps share: the tiny profile, scratch 2D weights (Pri3D's would be pretrained first), a short evaluation
COMMON = ["profile=tiny", "encoder2d=scratch", "data.workers=1", "eval.max_pairs=1", "eval.n_points=[250]",
          "runtime.report_on_end=false"]
MAIN = ["+experiment=main_results", "hydra.sweeper.params.features=deep"]
WINDOW = ["+experiment=window_size", "hydra.sweeper.params.window_size=11"]


def _held_elsewhere(lock: Path) -> bool:
    """Whether another opener holds ``lock`` (a second, non-blocking FileLock on it times out)."""
    from filelock import FileLock, Timeout

    other = FileLock(str(lock), timeout=0)
    try:
        other.acquire()
    except Timeout:
        return True
    other.release()
    return False


@pytest.fixture(scope="module")
def sweeps(tiny_root, tmp_path_factory):
    import pcrcg.models.train as train_module

    root = tmp_path_factory.mktemp("real")
    uri = f"sqlite:///{root}/mlflow.db"
    out = {"root": root, "uri": uri, "lock_held_in_training": []}
    real_train = train_module.train

    def train_watching_the_lock(cfg, *, out_dir, **kw):
        out["lock_held_in_training"].append(_held_elsewhere(Path(out_dir).parent / ".lock"))
        return real_train(cfg, out_dir=out_dir, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", uri)
        mp.setattr(train_module, "train", train_watching_the_lock)
        for name, sweep in (("main", MAIN), ("window", WINDOW)):
            args = ["--config-path", str(CONF_DIR), *sweep, *COMMON, f"data.root={tiny_root}", f"hydra.sweep.dir={root}/multirun/{name}", "-m"]
            out[f"rc_{name}"] = run_cli(args, root, mp)
            out[f"status_{name}"] = read_status_files(root / "multirun" / name)
    return out


def _only_run(uri: str, experiment: str):
    runs = tracked_runs(uri, experiment)
    assert len(runs) == 1, [r.info.run_name for r in runs]
    return runs[0]


def test_both_sweeps_finish_and_train_once_under_the_cache_lock(sweeps):
    assert (sweeps["rc_main"], sweeps["rc_window"]) == (0, 0)
    assert [s["status"] for s in sweeps["status_main"]] == ["finished"]
    assert [s["status"] for s in sweeps["status_window"]] == ["finished"]
    assert sweeps["lock_held_in_training"] == [True]  # one training, while the cache's lock was held


def test_the_checkpoint_cache_is_keyed_by_the_training_hash(sweeps, tiny_root):
    from pcrcg.config import load_run_config
    from pcrcg.models.train import read_checkpoint
    from pcrcg.pipeline import train_key
    from pcrcg.tracking.git import code_version

    overrides = [*COMMON, f"data.root={tiny_root}"]
    key = train_key(load_run_config(["+experiment=main_results", "features=deep", *overrides]))
    assert train_key(load_run_config(["+experiment=window_size", "window_size=11", *overrides])) == key
    caches = sorted(p.name for p in (sweeps["root"] / "checkpoints").iterdir())
    assert caches == [key]
    cache = sweeps["root"] / "checkpoints" / key
    assert {"model.ckpt", "history.json", "source.json", ".lock"} <= {p.name for p in cache.iterdir()}
    main = _only_run(sweeps["uri"], "main_results")
    assert json.loads((cache / "source.json").read_text()) == {"run_id": main.info.run_id, "experiment": "main_results",
                                                              "train_hash": key, "code_version": code_version()}
    read_checkpoint(cache / "model.ckpt")  # a checkpoint of this project, read safely
    history = json.loads((cache / "history.json").read_text())
    assert [step for step, _ in history["train/loss"]] == [0, 1, 2, 3]  # the tiny profile's 4 steps


def test_the_second_sweep_reuses_the_first_sweeps_model(sweeps):
    main, window = _only_run(sweeps["uri"], "main_results"), _only_run(sweeps["uri"], "window_size")
    key = next((sweeps["root"] / "checkpoints").iterdir()).name
    assert "checkpoint_reused" not in main.data.tags
    assert window.data.tags["checkpoint_reused"] == str(sweeps["root"] / "checkpoints" / key / "model.ckpt")
    assert window.data.tags["checkpoint_run"] == main.info.run_id
    from mlflow.tracking import MlflowClient

    client = MlflowClient(sweeps["uri"])
    assert {a.path for a in client.list_artifacts(main.info.run_id, "checkpoint")} == {"checkpoint/model.ckpt"}
    assert {a.path for a in client.list_artifacts(window.info.run_id, "checkpoint")} == \
        {"checkpoint/reused_from.json"}
    # main_results' PCR-CG row and window_size 11 are one config filed under two tables: same hash, and
    # the same model on the same pairs gives the same estimates, byte for byte
    assert main.data.tags["config_hash"] == window.data.tags["config_hash"]
    from pcrcg.tracking.git import code_version

    assert main.data.tags["code_version"] == window.data.tags["code_version"] == code_version()
    estimates = {}
    for name in ("main", "window"):
        (status,) = sweeps[f"status_{name}"]
        est_dir = Path(status["output_dir"]) / "eval" / "learned"
        estimates[name] = {p.relative_to(est_dir).as_posix(): p.read_text() for p in est_dir.rglob("est.log")}
    assert sorted(estimates["main"]) == sorted(estimates["window"]) and len(estimates["main"]) == 2
    assert estimates["main"] == estimates["window"]
    assert main.data.metrics["3DMatch/n_evaluated"] == window.data.metrics["3DMatch/n_evaluated"] == 1.0
