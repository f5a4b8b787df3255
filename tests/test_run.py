"""End to end at the tiny profile: sweep -> MLflow -> report, failures, relaunch, single runs.

The stages are fakes (tests/test_run_support.py) that report known metrics, so every number
below is checked exactly; the sweep goes through the real CLI (``python -m pcrcg.run ... -m``,
in-process), Hydra, the multirun callback, MLflow (a SQLite store in tmp_path) and the report.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pandas as pd
import pytest
import torch

from test_run_support import (FAKES, expected_rr, make_conf, native_threads, read_status_files, run_cli, stand_in_pri3d,
                              tracked_runs)

N_POINTS = (5000, 2500, 1000, 500, 250)
BENCHES = ("3DMatch", "3DLoMatch")


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """window_size sweep three times (one job failing, relaunch, relaunch) + a backbone_2d sweep."""
    root = tmp_path_factory.mktemp("e2e")
    conf = make_conf(root / "conf")
    uri = f"sqlite:///{root}/mlflow.db"
    out = {"root": root, "conf": conf, "uri": uri}
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", uri)

        def sweep_args(name: str, exp: str = "window_size") -> list[str]:
            return ["--config-path", str(conf), f"+experiment={exp}", "profile=tiny", *FAKES,
                    f"hydra.sweep.dir={root}/multirun/{name}", "-m"]

        # window_size runs with Pri3D weights (its caption): a stand-in where the default points; the backbone sweep
        # below runs without it (pri3d: not run)
        pri3d = stand_in_pri3d(root)
        mp.setenv("PCRCG_FAKE_FAIL", "window_size=7")
        out["rc_fail"] = run_cli(sweep_args("a"), root, mp)
        out["status_fail"] = read_status_files(root / "multirun" / "a")
        out["train_calls_1"] = (root / "train_calls.txt").read_text().splitlines()
        out["report_md_1"] = (root / "reports" / "window_size.md").read_text()
        mp.delenv("PCRCG_FAKE_FAIL")
        out["rc_retry"] = run_cli(sweep_args("b"), root, mp)
        out["status_retry"] = read_status_files(root / "multirun" / "b")
        out["train_calls_2"] = (root / "train_calls.txt").read_text().splitlines()
        out["rc_again"] = run_cli(sweep_args("c"), root, mp)
        out["status_again"] = read_status_files(root / "multirun" / "c")
        out["train_calls_3"] = (root / "train_calls.txt").read_text().splitlines()
        pri3d.unlink()
        out["rc_backbone"] = run_cli(sweep_args("d", "backbone_2d"), root, mp)
        out["status_backbone"] = read_status_files(root / "multirun" / "d")
    return out


def _by_name(runs):
    out: dict[str, list] = {}
    for r in runs:
        out.setdefault(r.info.run_name, []).append(r)
    return out


def test_failing_job_leaves_the_others_finished(sweep):
    assert sweep["rc_fail"] == 1  # the command reports the failure at the end ...
    status = {s["run_name"]: s["status"] for s in sweep["status_fail"]}
    assert status == {"window_size=3": "finished", "window_size=7": "failed",
                      "window_size=11": "finished", "window_size=17": "finished"}  # ... after all jobs ran
    assert len(sweep["train_calls_1"]) == 4
    runs = _by_name(tracked_runs(sweep["uri"], "window_size"))
    failed = [r for r in runs["window_size=7"] if r.info.status == "FAILED"]
    assert len(failed) == 1
    assert failed[0].data.tags["error"] == "fake evaluate failure for window_size=7"
    assert failed[0].data.tags["error_type"] == "RuntimeError"
    # the report written after the sweep shows the failure as a dash with the reason
    md = sweep["report_md_1"]
    assert "failed: fake evaluate failure for window_size=7" in md
    assert "| PCR-CG 7x7 (ours) | — [1] |" in md.replace(" — [1] |" * 4, "")


def test_relaunch_runs_only_what_is_missing(sweep):
    assert sweep["rc_retry"] == 0
    status = {s["run_name"]: s["status"] for s in sweep["status_retry"]}
    assert status == {"window_size=3": "skipped", "window_size=7": "finished",
                      "window_size=11": "skipped", "window_size=17": "skipped"}
    assert len(sweep["train_calls_2"]) == 5  # one new training
    assert sweep["rc_again"] == 0
    assert {s["status"] for s in sweep["status_again"]} == {"skipped"}
    assert sweep["train_calls_3"] == sweep["train_calls_2"]  # the same command again trains nothing


def test_finished_runs_carry_params_tags_metrics_and_artifacts(sweep):
    runs = [r for r in tracked_runs(sweep["uri"], "window_size") if r.info.status == "FINISHED"]
    assert sorted(r.info.run_name for r in runs) == ["window_size=11", "window_size=17", "window_size=3",
                                                      "window_size=7"]
    in_checkout = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, cwd=Path(__file__).parent)
    hashes = set()
    for r in runs:
        ws = int(r.info.run_name.split("=")[1])
        tags, params, metrics = r.data.tags, r.data.params, r.data.metrics
        assert tags["experiment"] == "window_size" and tags["profile"] == "tiny"
        assert tags["label"] == "PCR-CG" and tags["method"] == "learned"
        if in_checkout.returncode == 0:  # the commit the checkout was at (HEAD or, if one landed since, before it)
            is_ancestor = subprocess.run(["git", "merge-base", "--is-ancestor", tags["git_sha"], "HEAD"],
                                         capture_output=True, cwd=Path(__file__).parent)
            assert len(tags["git_sha"]) == 40 and is_ancestor.returncode == 0, tags["git_sha"]
        else:  # an unpacked copy
            assert tags["git_sha"] == "unknown"
        hashes.add(tags["config_hash"])
        assert params["window_size"] == str(ws) and params["profile.name"] == "tiny"
        assert params["features.name"] == "deep" and params["projection.name"] == "explicit"
        assert set(json.loads(params["eval.n_points"])) <= set(N_POINTS)  # the profile's sizes
        assert params["protocol.3DLoMatch.n_pairs"] == "12"
        for b in BENCHES:
            for n in N_POINTS:
                assert metrics[f"{b}/rr_{n}"] == pytest.approx(expected_rr(ws, 0, n, b))
                assert metrics[f"{b}/fmr_{n}"] == 90.0 and metrics[f"{b}/ir_{n}"] == 30.0
            assert metrics[f"{b}/rre"] == 2.0 and metrics[f"{b}/rte"] == 0.07
        assert metrics["color_coverage"] == pytest.approx(0.6)
        assert metrics["time/total_s"] > 0
        for stage in ("prepare", "check_inputs", "train", "evaluate", "total"):
            assert metrics[f"time/{stage}_cpu_s"] >= 0, stage
        assert metrics["time/total_cpu_s"] >= metrics["time/train_cpu_s"] + metrics["time/evaluate_cpu_s"] - 1e-6
        client = __import__("mlflow").tracking.MlflowClient(sweep["uri"])
        curve = client.get_metric_history(r.info.run_id, "train/loss")
        assert [m.value for m in sorted(curve, key=lambda m: m.step)] == [1.0, 0.5, 0.25]
        arts = {a.path for a in client.list_artifacts(r.info.run_id)}
        assert {"config", "checkpoint", "est_logs", "plots", "metrics.json"} <= arts
        cfg_files = {a.path for a in client.list_artifacts(r.info.run_id, "config")}
        assert {"config/config.yaml", "config/overrides.yaml", "config/hydra"} <= cfg_files
        est = {a.path for a in client.list_artifacts(r.info.run_id, "est_logs/3DLoMatch/scene-a")}
        assert est == {"est_logs/3DLoMatch/scene-a/est.log"}
        assert {a.path for a in client.list_artifacts(r.info.run_id, "plots")} == {"plots/recall_vs_points.png"}
    assert len(hashes) == 4


def test_report_after_the_sweep(sweep):
    reports = sweep["root"] / "reports"
    for suffix in ("md", "tex", "csv"):
        assert (reports / f"window_size.{suffix}").is_file()
    assert (reports / "window_size_recall.png").stat().st_size > 1000
    assert (reports / "window_size_coverage.png").is_file()
    df = pd.read_csv(reports / "window_size.csv")
    assert len(df) == 4 * 5 and (df["status"] == "ok").all()
    cell = df[(df["variant"] == "11x11") & (df["n_points"] == 1000)].iloc[0]
    assert cell["paper"] == 69.0
    assert cell["ours_mean"] == pytest.approx(expected_rr(11, 0, 1000, "3DLoMatch"), abs=1e-3)
    assert cell["diff"] == pytest.approx(cell["ours_mean"] - 69.0, abs=1e-3)
    assert cell["profiles"] == "tiny" and len(cell["run_ids"]) == 32 and len(cell["config_hashes"]) == 16


def test_missing_weights_is_reported_as_not_run(sweep):
    assert sweep["rc_backbone"] == 0  # "not run" is a reason, not a failure of the sweep
    status = {s["run_name"]: s["status"] for s in sweep["status_backbone"]}
    assert status == {f"encoder2d={e} encoder2d.training={t}": ("finished" if e == "scratch" else "not_run")
                      for e in ("scratch", "imagenet", "pri3d") for t in ("detached", "end_to_end")}
    runs = _by_name(tracked_runs(sweep["uri"], "backbone_2d"))
    rec = runs["encoder2d=imagenet encoder2d.training=detached"][0]
    assert rec.info.status == "FAILED" and rec.data.tags["not_run"] == "true"
    assert "encoder2d.weights" in rec.data.tags["error"]
    md = (sweep["root"] / "reports" / "backbone_2d.md").read_text()
    assert "not run: invalid config value encoder2d.weights=None" in md
    df = pd.read_csv(sweep["root"] / "reports" / "backbone_2d.csv")
    assert set(df[df["status"] == "missing"]["variant"]) == {"ImageNet", "Pri3D", "ImageNet, end to end",
                                                              "Pri3D, end to end", "DISK"}


def test_classical_baseline_single_run_and_single_run_failure(sweep, monkeypatch, capsys):
    root, conf = sweep["root"], sweep["conf"]
    monkeypatch.setenv("MLFLOW_TRACKING_URI", sweep["uri"])
    calls = len((root / "train_calls.txt").read_text().splitlines())
    args = ["--config-path", str(conf), "method=fpfh", "profile=tiny", "experiment_name=baselines", *FAKES,
            f"hydra.run.dir={root}/single/fpfh"]
    assert run_cli(args, root, monkeypatch) == 0
    out = capsys.readouterr().out
    assert "open the UI: mlflow ui --backend-store-uri " + sweep["uri"] in out
    assert len((root / "train_calls.txt").read_text().splitlines()) == calls  # no training
    runs = tracked_runs(sweep["uri"], "baselines")
    assert len(runs) == 1 and runs[0].info.status == "FINISHED" and runs[0].data.tags["label"] == "FPFH"
    assert runs[0].info.run_name == "method=fpfh"
    # the same single run again is skipped
    assert run_cli(args, root, monkeypatch) == 0
    assert "skipped" in capsys.readouterr().out
    # a failing single run is recorded and the command fails
    monkeypatch.setenv("PCRCG_FAKE_FAIL", "method=icp")
    bad = ["--config-path", str(conf), "method=icp", "profile=tiny", "experiment_name=baselines", *FAKES,
           f"hydra.run.dir={root}/single/icp"]
    assert run_cli(bad, root, monkeypatch) == 1
    runs = _by_name(tracked_runs(sweep["uri"], "baselines"))
    assert runs["method=icp"][0].info.status == "FAILED"


def test_without_tracking(tmp_path, monkeypatch):
    conf = make_conf(tmp_path / "conf")
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    args = ["--config-path", str(conf), "logger=none", "method=sift_dlt", "profile=tiny", *FAKES,
            f"hydra.run.dir={tmp_path}/out"]
    assert run_cli(args, tmp_path, monkeypatch) == 0
    assert not (tmp_path / "mlflow.db").exists()
    data = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert data["metrics"]["3DMatch/rr"] == pytest.approx(expected_rr(11, 0, 5000, "3DMatch"))
    assert (tmp_path / "out" / "pcrcg_status.json").is_file()
    # the stage times stay with the run's files where no store keeps them
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert {"time/evaluate_s", "time/evaluate_cpu_s", "time/total_s"} <= set(timings)
    assert 0 <= timings["time/evaluate_s"] <= timings["time/total_s"]


def test_a_resumed_trainings_earlier_seconds_stay_with_the_stage_times(tmp_path, monkeypatch):
    """The seconds a resumed training's earlier starts spent are logged with the stage times (timings.json and
    the store's time/ metrics), and the store's readers count them in the run's total."""
    from pcrcg.pipeline import run_seconds
    from pcrcg.tracking.store import client

    conf = make_conf(tmp_path / "conf")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    args = ["--config-path", str(conf), "profile=tiny", FAKES[0], "stages.train=test_run_support.resumed_train",
            FAKES[2], "experiment_name=resumed", f"hydra.run.dir={tmp_path}/out"]
    assert run_cli(args, tmp_path, monkeypatch) == 0
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["time/train_earlier_s"] == 400.0 and timings["time/train_earlier_cpu_s"] == 300.0
    c = client(uri)
    (run,) = c.search_runs([c.get_experiment_by_name("resumed").experiment_id])
    m = run.data.metrics
    assert m["time/train_earlier_s"] == 400.0 and m["train/resumed_from_step"] == 5.0
    assert run_seconds(m) == pytest.approx(m["time/total_s"] + 400.0)


def test_every_stage_runs_with_the_trainers_threads(tmp_path, monkeypatch):
    """A run whose training is skipped (a reused checkpoint, here a fake train stage that sets nothing)
    still evaluates with ``trainer.num_threads`` (the tiny profile's 1), torch's and the native pools'
    (OpenBLAS, OpenMP) alike, and the caller's numbers are back afterwards; ``null`` leaves them alone."""
    import numpy as np  # noqa: F401  (NumPy's and SciPy's OpenBLAS loaded, so that their pools are set here)
    import scipy.linalg  # noqa: F401
    import torch
    from threadpoolctl import threadpool_limits

    conf = make_conf(tmp_path / "conf")
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with threadpool_limits(limits=2):  # every native pool at 2, whatever the environment set
            for k, threads in enumerate(("1", "null")):
                args = ["--config-path", str(conf), "logger=none", "profile=tiny", *FAKES[:2],
                        "stages.evaluate=test_run_support.threads_evaluate", f"profile.train.num_threads={threads}",
                        f"hydra.run.dir={tmp_path}/out{k}"]
                assert run_cli(args, tmp_path, monkeypatch) == 0
                assert torch.get_num_threads() == 2 and native_threads() == "2"
        assert (tmp_path / "eval_threads.txt").read_text().splitlines() == ["1 1", "2 2"]
    finally:
        torch.set_num_threads(before)


@pytest.mark.slow
def test_parallel_joblib_sweep_writes_one_store(tmp_path, monkeypatch):
    """hydra/launcher=joblib2: two worker processes, one SQLite store created by the parent."""
    conf = make_conf(tmp_path / "conf")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    tests_dir = str(Path(__file__).resolve().parent)
    monkeypatch.setenv("PYTHONPATH", tests_dir)
    stand_in_pri3d(tmp_path)  # the window_size experiment's Pri3D weights (the fake stages never read them)
    args = ["--config-path", str(conf), "+experiment=window_size", "profile=tiny", *FAKES,
            "hydra/launcher=joblib2", f"hydra.sweep.dir={tmp_path}/multirun", "runtime.report_on_end=false", "-m"]
    assert run_cli(args, tmp_path, monkeypatch) == 0
    runs = tracked_runs(uri, "window_size")
    assert len(runs) == 4 and all(r.info.status == "FINISHED" for r in runs)
    assert all(len(r.data.metrics) >= 2 * (3 * 5 + 3) for r in runs)


def test_run_name_says_what_differs():
    from pcrcg.pipeline import run_name

    assert run_name(["window_size=7", "+experiment=window_size", "profile=tiny"]) == "window_size=7"
    assert run_name(["+experiment=projection", "features=rgb", "projection=implicit", "seed=1",
                     "logger.tracking_uri=x", "stages.train=a.b", "hydra.verbose=true"]) == \
        "features=rgb projection=implicit seed=1"
    assert run_name([]) == "defaults"


def test_method_label():
    from pcrcg.pipeline import method_label

    assert method_label({"method": "learned", "features": {"name": "none"}, "projection": {"name": "explicit"}}) \
        == "Predator"
    assert method_label({"method": "learned", "features": {"name": "deep"}, "projection": {"name": "explicit"}}) \
        == "PCR-CG"
    assert method_label({"method": "color_icp"}) == "ColorICP"


def test_cli_argument_parsing(tmp_path):
    from pcrcg.config import CONF_DIR
    from pcrcg.cli import command_line_config_dirs as cli_search_dirs
    from pcrcg.cli import command_line_overrides as cli_overrides

    argv = ["--config-path", str(tmp_path), "-cn", "run", "+experiment=views", "views=1,2", "-m", "--multirun"]
    assert cli_overrides(argv) == ["+experiment=views", "views=1,2"]
    assert cli_search_dirs(argv) == [tmp_path.resolve()]
    assert cli_search_dirs([f"--config-dir={tmp_path}"]) == [CONF_DIR, tmp_path.resolve()]


def test_bad_value_in_an_experiment_sweep_stops_before_any_job(tmp_path, monkeypatch, capsys):
    conf = make_conf(tmp_path / "conf")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path}/mlflow.db")
    args = ["--config-path", str(conf), "+experiment=window_size", "hydra.sweeper.params.window_size='3,8'",
            *FAKES, f"hydra.sweep.dir={tmp_path}/multirun", "-m"]
    assert run_cli(args, tmp_path, monkeypatch) == 2
    err = capsys.readouterr().err
    assert "invalid config value window_size=8" in err and "no job was started" in err
    assert not (tmp_path / "mlflow.db").exists()
    assert not list(tmp_path.rglob("pcrcg_status.json"))


def test_a_long_table_title_is_wrapped_to_the_figure_width():
    """A table's title ran off both edges of its recall and coverage figures; it is broken into lines."""
    from pcrcg.plots.recall import _wrap

    title = "CoFiNet with and without the projection module (3DLoMatch registration recall; RANSAC on N)"
    text, lines = _wrap(title, 3.5, 9)
    assert lines > 1 and text.replace("\n", " ") == title
    assert max(len(line) for line in text.splitlines()) <= int(3.5 * 72 / (0.55 * 9))
    assert _wrap("Table 1", 10.0, 9) == ("Table 1", 1)


def test_clock_counts_cpu_seconds_not_waiting_and_ended_children():
    """A stage's CPU seconds: its own work and its ended child processes' (loader workers), not the time
    it waited (a sleep here; a core taken by another lane in a sweep)."""
    import sys
    import time

    from pcrcg.pipeline import Clock

    clock = Clock()
    time.sleep(0.3)
    assert clock.wall() >= 0.3 and clock.cpu() < 0.1
    clock = Clock()
    busy = time.process_time()
    while time.process_time() - busy < 0.2:
        pass
    assert clock.cpu() >= 0.2
    clock = Clock()
    subprocess.run([sys.executable, "-c", "import time\nt = time.process_time()\n"
                    "while time.process_time() - t < 0.3: pass"], check=True)
    spent = clock.metrics("stage")
    assert set(spent) == {"time/stage_s", "time/stage_cpu_s"}
    assert spent["time/stage_cpu_s"] >= 0.3 and spent["time/stage_s"] >= 0.3


def test_run_seconds_add_a_resumed_trainings_earlier_starts():
    """A run whose training resumed counts what its earlier starts spent up to the checkpoint, in its training
    and total seconds (not in the other stages'); a run that did not resume, and one that logged no time, as is."""
    from pcrcg.pipeline import run_seconds

    m = {"time/total_s": 100.0, "time/total_cpu_s": 80.0, "time/train_s": 10.0, "time/train_cpu_s": 9.0,
         "time/evaluate_s": 60.0, "time/train_earlier_s": 500.0, "time/train_earlier_cpu_s": 450.0}
    assert run_seconds(m) == 600.0 and run_seconds(m, cpu=True) == 530.0
    assert run_seconds(m, "train") == 510.0 and run_seconds(m, "train", cpu=True) == 459.0
    assert run_seconds(m, "evaluate") == 60.0 and run_seconds(m, "evaluate", cpu=True) is None
    assert run_seconds({"time/total_s": 100.0}) == 100.0 and run_seconds({}) is None
