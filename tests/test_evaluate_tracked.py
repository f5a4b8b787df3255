"""``python -m pcrcg.evaluate mode=tracked``: tracked runs evaluated again on another data root.

A real PCR-CG run (rgb lifted from the views, 4 training steps at the tiny profile, one pair per
benchmark at N = 250) is tracked in a temporary MLflow store, then evaluated on a second data root (a
copy of the tiny data set under another name) with every pair: its metrics appear in the same run
under ``other/`` and equal what ``mode=benchmark method=learned`` gives for the same checkpoint; a
second call skips the run. The error cases use hand-made runs in a fresh store (no training).
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, compose
from pcrcg.config import CONF_DIR
from pcrcg.errors import ConfigError, DataError
from test_run_support import run_cli, tracked_runs

RUN = ["experiment_name=main_results", "profile=tiny", "encoder2d=scratch", "features=rgb", "projection=implicit",
       "data.workers=1", "eval.max_pairs=1", "eval.n_points=[250]", "runtime.report_on_end=false"]
NAME = "other"


def _tracked(overrides: list[str]) -> dict:
    from pcrcg.evaluate import run

    out = run(compose("evaluate", ["mode=tracked", "progress=false", *overrides]))
    json.dumps(out, allow_nan=False)  # the JSON last line, strict
    return out


@pytest.fixture(scope="module")
def tracked(tiny_root, tmp_path_factory):
    """A finished tracked run of a tiny PCR-CG model, and a second data root (``other``)."""
    base = tmp_path_factory.mktemp("tracked")
    uri = f"sqlite:///{base}/mlflow.db"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", uri)
        rc = run_cli(["--config-path", str(CONF_DIR), *RUN, f"data.root={tiny_root}",
                      f"hydra.run.dir={base}/outputs/run"], base, mp)
    assert rc == 0
    (run,) = tracked_runs(uri, "main_results")
    other = base / NAME
    shutil.copytree(tiny_root, other, symlinks=True)
    return {"base": base, "uri": uri, "run": run, "other": other}


@pytest.fixture
def in_store(tracked, monkeypatch):
    """Work in the run's folder with its store (as a user would: MLFLOW_TRACKING_URI)."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", tracked["uri"])
    monkeypatch.chdir(tracked["base"])
    return tracked


def _client(uri: str):
    from mlflow.tracking import MlflowClient

    return MlflowClient(uri)


def _same(a: float | None, b: float | None) -> bool:
    if a is None or b is None or math.isnan(a) or math.isnan(b):
        return (a is None or math.isnan(a)) and (b is None or math.isnan(b))
    return a == pytest.approx(b, abs=1e-9)


@pytest.mark.slow
def test_every_pair_of_the_other_root_lands_in_the_same_run(in_store, tmp_path):
    from pcrcg.evaluation.metrics import load_benchmark
    from pcrcg.evaluation.pairs import PAIR_COLUMNS

    rid, other = in_store["run"].info.run_id, in_store["other"]
    res = _tracked(["experiments=[main_results]", f"data.root={other}", f"name={NAME}"])
    assert [e["run_id"] for e in res["evaluated"]] == [rid] and res["skipped"] == [] and res["failed"] == []
    assert res["evaluated"][0]["checkpoint_from"] == "artifact checkpoint/model.ckpt"
    run = _client(in_store["uri"]).get_run(rid)
    assert run.info.status == "FINISHED"
    # exactly the keys the run logs for its own evaluation, under the prefix
    own = {k for k in in_store["run"].data.metrics if k.split("/")[0] in ("3DMatch", "3DLoMatch") or k == "color_coverage"}
    new = {k[len(NAME) + 1:] for k in run.data.metrics if k.startswith(f"{NAME}/")}
    assert new == own and "3DMatch/rr_250" in new and "color_coverage" in new
    # every pair of the other root (the run itself evaluated one per benchmark)
    for b in ("3DMatch", "3DLoMatch"):
        n = sum(len(g.pairs) for g in load_benchmark(other / "benchmarks" / b).values())
        assert in_store["run"].data.metrics[f"{b}/n_evaluated"] == 1
        assert run.data.metrics[f"{NAME}/{b}/n_evaluated"] == n > 1
    # the numbers mode=benchmark prints for the same checkpoint, data root and settings
    ckpt = Path(res["evaluated"][0]["checkpoint"])
    from pcrcg.evaluate import run as evaluate_run

    bench = evaluate_run(compose("evaluate", ["profile=tiny", "mode=benchmark", "method=learned", f"checkpoint={ckpt}",
                                              f"data.root={other}", "registration.n_points=[250]",
                                              f"out_dir={tmp_path / 'bench'}"]))
    for b, values in bench["benchmarks"].items():
        assert math.isfinite(values["ir_250"]) and values["n_pairs"] == run.data.metrics[f"{NAME}/{b}/n_pairs"]
        for k, v in values.items():
            assert _same(run.data.metrics[f"{NAME}/{b}/{k}"], v), (b, k)
    assert _same(run.data.metrics[f"{NAME}/color_coverage"], bench["color_coverage"])
    saved = json.loads((tmp_path / "bench" / "metrics.json").read_text())["metrics"]  # every metric, not only those printed
    assert {f"{NAME}/{k}" for k in saved} == {k for k in run.data.metrics if k.startswith(f"{NAME}/")}
    for k, v in saved.items():
        assert k.split("/")[-1].startswith("seconds_per_pair") or _same(run.data.metrics[f"{NAME}/{k}"], v), k
    assert 0.0 < bench["color_coverage"] <= 1.0  # the color model read the other root's views
    # the per-pair outcomes and the estimates as artifacts, the data root as a tag
    client = _client(in_store["uri"])
    assert {a.path for a in client.list_artifacts(rid, f"{NAME}/pairs")} == \
        {f"{NAME}/pairs/3DMatch.csv", f"{NAME}/pairs/3DLoMatch.csv"}
    local = Path(client.download_artifacts(rid, f"{NAME}/pairs/3DMatch.csv", str(tmp_path)))
    with open(local) as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == PAIR_COLUMNS and len(rows) == run.data.metrics[f"{NAME}/3DMatch/n_pairs"]
    est = [a.path for a in client.list_artifacts(rid, f"{NAME}/estimates/3DMatch/250")]
    assert est and all(p.startswith(f"{NAME}/estimates/3DMatch/250/") for p in est)
    manifest = json.loads((other / "manifest.json").read_text())
    assert run.data.tags[f"{NAME}.data_root"] == f"{other.resolve()} params_hash={manifest['params_hash']}"
    from pcrcg.tracking.git import code_version

    assert run.data.tags[f"{NAME}.code_version"] == code_version()
    # the run's own results are untouched
    assert _same(run.data.metrics["3DMatch/rr_250"], in_store["run"].data.metrics["3DMatch/rr_250"])
    assert run.data.metrics["3DMatch/n_evaluated"] == 1


@pytest.mark.slow
def test_a_second_call_skips_and_force_redoes(in_store):
    rid, other = in_store["run"].info.run_id, in_store["other"]
    env = {**os.environ, "MLFLOW_TRACKING_URI": in_store["uri"], "PYTHONPATH": str(REPO)}
    args = [sys.executable, "-m", "pcrcg.evaluate", "mode=tracked", "experiments=[main_results]",
            f"data.root={other}", f"name={NAME}", f"hydra.run.dir={in_store['base']}/outputs/eval"]
    first = subprocess.run(args, cwd=in_store["base"], env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-2000:]
    second = subprocess.run(args, cwd=in_store["base"], env=env, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stderr[-2000:]
    out = json.loads(second.stdout.strip().splitlines()[-1])  # the last line is one JSON object
    assert out["evaluated"] == [] and [s["run_id"] for s in out["skipped"]] == [rid]
    assert "already has metrics under other/" in out["skipped"][0]["reason"]
    assert f"skip run {rid}" in second.stdout
    client = _client(in_store["uri"])
    before = len(client.get_metric_history(rid, f"{NAME}/3DLoMatch/ir_250"))
    res = _tracked(["experiments=[main_results]", f"data.root={other}", f"name={NAME}", "force=true"])
    assert [e["run_id"] for e in res["evaluated"]] == [rid]
    history = client.get_metric_history(rid, f"{NAME}/3DLoMatch/ir_250")
    assert len(history) == before + 1 and history[-1].value == history[0].value  # same seed, same numbers


# --------------------------------------------------------------------------- bad input, hand-made runs


@pytest.fixture
def store(tmp_path, monkeypatch, tiny_root):
    """A fresh store with experiment ``main_results`` and a helper adding a FINISHED learned run."""
    import yaml

    from pcrcg.tracking.hashing import to_plain
    from pcrcg.tracking.tracker import RunTracker

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.chdir(tmp_path)
    tracker = RunTracker(uri, "main_results")
    config = to_plain(compose("run", ["profile=tiny", f"data.root={tiny_root}"]))

    def add(checkpoint: bytes | None = None, method: str = "learned", overrides: str | None = None) -> str:
        rid = tracker.start("hand-made", {"method": method, **({"overrides": overrides} if overrides else {})})
        cdir = tmp_path / rid
        cdir.mkdir()
        (cdir / "config.yaml").write_text(yaml.safe_dump({**config, "method": method}))
        tracker.log_artifact(rid, cdir / "config.yaml", "config")
        if checkpoint is not None:
            (cdir / "model.ckpt").write_bytes(checkpoint)
            tracker.log_artifact(rid, cdir / "model.ckpt", "checkpoint")
        tracker.finish(rid)
        return rid

    return {"uri": uri, "add": add, "base": tmp_path}


def test_a_run_without_its_checkpoint_is_skipped_and_a_classical_run_is_run_again(store, tiny_root):
    """A learned run whose model is gone is reported and skipped; a classical method (ICP from the identity:
    no model) is run again on the other root, into its run, as a learned run's evaluation is."""
    from pcrcg.evaluation.tracked import CLASSICAL_FROM

    gone = store["add"]()
    tagged = store["add"](overrides="features=none +experiment=main_results profile=tiny seed=1")
    icp = store["add"](method="icp")
    res = _tracked(["experiments=[main_results]", f"data.root={tiny_root}", f"name={NAME}"])
    assert res["failed"] == []
    reasons = {s["run_id"]: s["reason"] for s in res["skipped"]}
    assert set(reasons) == {gone, tagged}
    assert reasons[gone].startswith("checkpoint not found (looked at: artifact checkpoint/model.ckpt")
    assert reasons[gone].endswith(")")  # no overrides tag: no command
    # a run that says how it was launched: the command that trains its config again, into a new run
    assert reasons[tagged].endswith("; to train it again into a new run of the same config (the report counts the "
                                    "newest): python -m pcrcg.run features=none +experiment=main_results "
                                    "profile=tiny seed=1 logger.skip_finished=false")
    (done,) = res["evaluated"]
    assert done["run_id"] == icp and done["checkpoint"] is None
    run = _client(store["uri"]).get_run(icp)
    assert {f"{NAME}/3DMatch/rr", f"{NAME}/3DLoMatch/rr"} <= set(run.data.metrics)
    assert run.data.tags[f"{NAME}.checkpoint"] == CLASSICAL_FROM
    again = _tracked(["experiments=[main_results]", f"data.root={tiny_root}", f"name={NAME}"])
    assert again["evaluated"] == [] and {s["run_id"] for s in again["skipped"]} == {gone, tagged, icp}


def test_a_corrupt_checkpoint_is_named_before_work(store, tiny_root):
    store["add"](checkpoint=b"not a checkpoint")
    with pytest.raises(DataError, match=r"checkpoint/model\.ckpt: refused by torch.load\(weights_only=True\)"):
        _tracked(["experiments=[main_results]", f"data.root={tiny_root}"])


def test_the_checkpoint_cache_entry_naming_the_run_is_found(store, tiny_root):
    rid = store["add"]()  # logger.log_checkpoint=false: no artifact, the cache's source.json names the run
    cache = store["base"] / "checkpoints" / "0123456789abcdef"
    cache.mkdir(parents=True)
    (cache / "model.ckpt").write_bytes(b"\x80\x04junk")
    (cache / "source.json").write_text(json.dumps({"run_id": rid}))
    with pytest.raises(DataError, match="0123456789abcdef/model.ckpt: "):
        _tracked(["experiments=[main_results]", f"data.root={tiny_root}"])
    (cache / "source.json").write_text(json.dumps({"run_id": "another-run"}))  # retrained since: another model
    res = _tracked(["experiments=[main_results]", f"data.root={tiny_root}"])
    assert res["skipped"][0]["reason"].startswith("checkpoint not found")


def test_bad_roots_and_experiments_are_one_line_errors(store, tiny_root, tmp_path):
    with pytest.raises(DataError, match="nowhere: data root \\(data.root\\) does not exist"):
        _tracked(["experiments=[main_results]", f"data.root={tmp_path / 'nowhere'}"])
    (tmp_path / "bare" / "splits").mkdir(parents=True)
    with pytest.raises(DataError, match="bare/benchmarks: holds no test benchmark"):
        _tracked(["experiments=[main_results]", f"data.root={tmp_path / 'bare'}"])
    with pytest.raises(ConfigError, match="experiments='window_size'.*main_results"):
        _tracked(["experiments=[main_results,window_size]", f"data.root={tiny_root}"])
    with pytest.raises(ConfigError, match="experiments=\\[\\]"):
        _tracked([f"data.root={tiny_root}"])
    with pytest.raises(ConfigError, match="name='a/b'"):
        _tracked(["experiments=[main_results]", f"data.root={tiny_root}", "name=a/b"])
    with pytest.raises(DataError, match="missing.db: MLflow store does not exist"):
        _tracked(["experiments=[main_results]", f"data.root={tiny_root}", f"logger.tracking_uri=sqlite:///{tmp_path}/missing.db"])
    assert not (tmp_path / "missing.db").exists()


def test_cli_error_is_one_line_exit_2(store, tiny_root):
    proc = subprocess.run(
        [sys.executable, "-m", "pcrcg.evaluate", "mode=tracked", "experiments=[nosuch]", f"data.root={tiny_root}",
         f"hydra.run.dir={store['base']}/hydra"],
        cwd=store["base"], env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert lines == [f"pcrcg.evaluate: error: invalid config value experiments='nosuch': allowed an experiment of "
                     f"the store {store['uri']}: Default, main_results"]
