"""pcrcg.benchmarks.speed: a store's runs read into stage rows, scaled to the reference workload, the summary's
verdicts, and bad input refused in one line."""

import subprocess
import sys
import time
from pathlib import Path

import pytest

from pcrcg.benchmarks import speed
from pcrcg.benchmarks.speed import REFERENCE, scaled, stage_rows, summary


def _log(c, exp_id: str, params: dict, metrics: dict, code: str = "c1", status: str = "FINISHED") -> str:
    from pcrcg.tracking.tracker import TAG_CODE

    run = c.create_run(exp_id, tags={TAG_CODE: code}, run_name=params.pop("_name", "r"))
    rid = run.info.run_id
    for k, v in params.items():
        c.log_param(rid, k, v)
    for k, v in metrics.items():
        c.log_metric(rid, k, v)
    c.set_terminated(rid, status)
    time.sleep(0.01)  # distinct start times: the newest run of a key is the one kept
    return rid


def _metrics(train_cpu: float | None, eval_cpu: float | None, steps: int = 1800, train_s: float = 900.0,
             evaluate_s: float = 300.0) -> dict:
    m = {"time/train_s": train_s, "time/evaluate_s": evaluate_s, "time/total_s": train_s + evaluate_s + 5,
         "train/global_step": float(steps), "3DMatch/n_pairs": 500.0, "3DLoMatch/n_pairs": 400.0,
         "real-redkitchen/3DMatch/n_pairs": 27.0}  # the real scene's pairs are not the run's evaluation
    if train_cpu is not None:
        m["time/train_cpu_s"] = train_cpu
    if eval_cpu is not None:
        m["time/evaluate_cpu_s"] = eval_cpu
    return m


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> str:
    from pcrcg.tracking.store import client

    uri = f"sqlite:///{tmp_path_factory.mktemp('speed') / 'runs.db'}"
    c = client(uri)
    exp = c.create_experiment("main_results")
    geo = {"method": "learned", "features.name": "none", "registration.ransac.score": "overlap"}
    _log(c, exp, {**geo, "_name": "older"}, _metrics(700.0, 200.0))
    _log(c, exp, {**geo, "_name": "newest"}, _metrics(540.0, 180.0))  # kept: newest of its key
    _log(c, exp, {**geo, "features.name": "deep", "_name": "deep"}, _metrics(None, None, steps=1500))
    _log(c, exp, {**geo, "_name": "other code"}, _metrics(1.0, 1.0), code="c2")
    _log(c, exp, {**geo, "_name": "killed"}, _metrics(1.0, 1.0), code="c1", status="KILLED")
    _log(c, exp, {"method": "fpfh", "features.name": "none", "_name": "fpfh"}, {"time/evaluate_s": 10.0})
    return uri


def test_stage_rows_keep_the_newest_finished_learned_run_per_key(store):
    rows = {(r["features"], r["score"]): r for r in stage_rows(store, code="c1")}
    assert set(rows) == {("none", "overlap"), ("deep", "overlap")}  # not fpfh, not the KILLED, not code c2
    geo = rows[("none", "overlap")]
    assert geo["name"] == "newest" and geo["code"] == "c1" and geo["steps"] == 1800
    assert geo["pairs"] == 900  # 500 + 400: the generated benchmarks only
    assert geo["cpu"] == {"train": 540.0, "evaluate": 180.0} and geo["wall"]["total"] == 1205.0
    assert rows[("deep", "overlap")]["cpu"] == {}
    # without a code version, the newest of every code: the c2 run is newer than "newest"
    assert {r["name"] for r in stage_rows(store)} == {"other code", "deep"}


def test_scaled_takes_cpu_seconds_where_logged_else_wall(store):
    rows = {r["features"]: r for r in stage_rows(store, code="c1")}
    s = scaled(rows["none"])
    assert s["kind"] == "cpu" and s["per_step_s"] == pytest.approx(0.3) and s["per_pair_s"] == pytest.approx(0.2)
    assert s["train_s"] == pytest.approx(0.3 * REFERENCE["steps"]) and s["evaluate_s"] == pytest.approx(36.0)
    d = scaled(rows["deep"], steps=150, pairs=90)
    assert d["kind"] == "wall" and d["train_s"] == pytest.approx(900.0 / 1500 * 150)
    assert d["evaluate_s"] == pytest.approx(300.0 / 900 * 90)


def test_summary_says_met_or_missed_by_how_much():
    lines = summary({"none": {"train_s": 100.0, "evaluate_s": 50.0, "kind": "cpu"},
                     "deep": {"train_s": 250.0, "evaluate_s": 100.0, "kind": "cpu"}})
    geo, deep = lines[2], lines[3]
    assert "| none | 450 | 150 (100 + 50, cpu) | 3.00x | <= 150 s (3x) | met |" == geo
    assert deep.startswith("| deep | 660 | 350 ") and "<= 330 s (2x)" in deep and deep.endswith("missed by 20 s |")


def test_the_reference_day_measured_here_replaces_the_other_machine_s_figures():
    from pcrcg.benchmarks.speed import _reference_seconds
    from pcrcg.errors import ConfigError

    here = _reference_seconds("none=360")
    assert here == {"none": 360.0} and _reference_seconds("") == {}
    lines = summary({"none": {"train_s": 100.0, "evaluate_s": 60.0, "kind": "cpu"},
                     "deep": {"train_s": 250.0, "evaluate_s": 80.0, "kind": "cpu"}}, here)
    assert lines[2] == "| none | 360 (here) | 160 (100 + 60, cpu) | 2.25x | <= 120 s (3x) | missed by 40 s |"
    assert lines[3].startswith("| deep | 660 | 330 ") and lines[3].endswith("| met |")  # no figure here: the day's
    for bad in ("none", "none=0", "none=x", "sift=300"):
        with pytest.raises(ConfigError, match="--reference"):
            _reference_seconds(bad)


def test_a_deep_reference_run_without_pri3d_weights_is_skipped_with_the_command(tmp_path, monkeypatch):
    monkeypatch.setattr(speed, "pri3d_weights", lambda profile: tmp_path / "none.pth")
    row, how = speed.reference_run("cpu", "deep", tmp_path)
    assert row is None and how.startswith("skipped: no Pri3D weights at ") and "python -m pcrcg.pretrain2d" in how
    assert not (tmp_path / "speed.db").exists()


def test_a_cold_reference_run_keeps_its_matches_and_pyramids_apart(tmp_path, monkeypatch):
    """``--cold``: the run gets an empty 2D match cache and pyramid folder of its own; without it the
    repository's, as the run finds them (the profile's defaults: nothing about them on the command line)."""
    import subprocess

    weights = tmp_path / "pri3d.pth"
    weights.write_bytes(b"")
    monkeypatch.setattr(speed, "pri3d_weights", lambda profile: weights)
    seen = []
    monkeypatch.setattr(speed, "_child", lambda cmd, env=None: seen.append(cmd) or subprocess.CompletedProcess(
        cmd, 1, "", "stopped by the test"))
    for color in ("none", "deep"):
        for cold in (False, True):
            row, how = speed.reference_run("cpu", color, tmp_path, cold=cold)
            assert row is None and how == "failed (exit 1): stopped by the test"
    given = [{a.split("=", 1)[0]: a.split("=", 1)[1] for a in cmd if "=" in a} for cmd in seen]
    assert [g.get("trainer.cache_dir") for g in given] == [None, str(tmp_path / "pyramids-none"), None,
                                                          str(tmp_path / "pyramids-deep")]
    assert [g.get("matcher2d.cache_dir") for g in given] == [None, None, None, str(tmp_path / "matches-deep")]


@pytest.mark.parametrize("args, needle", [
    (["--colors", "none,bogus"], "--colors"),
    (["--checkpoint", "/nonexistent/model.ckpt"], "/nonexistent/model.ckpt"),
    (["--store", "sqlite:////nonexistent/x.db"], "/nonexistent/x.db"),
    (["--eval-pairs", "0"], "--eval-pairs"),
    (["--skip", "trian"], "--skip"),
])
def test_bad_input_is_one_line_before_any_work(args, needle):
    skip = [] if "--skip" in args else ["--skip", "train,eval"]
    proc = subprocess.run([sys.executable, "-m", "pcrcg.benchmarks.speed", *args, *skip],
                          capture_output=True, text=True, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith("pcrcg.benchmarks.speed: error: ") and needle in lines[0]
    assert not Path("/nonexistent/x.db").exists()


def test_evaluation_before_and_after_register_every_pair_alike(tiny_root, tmp_path):
    """The evaluation section's two registrations (every row matched, no pruning / the defaults) on a tiny
    model's outputs give the same transforms at every N, and the section reports every N in wall and CPU."""
    from conftest import compose
    from pcrcg.benchmarks.evaluation import infer_outputs, registration_speed
    from pcrcg.config import N_POINTS
    from pcrcg.models.train import load_module, train

    cfg = compose("run", ["profile=tiny", "logger=none", f"data.root={tiny_root}", "trainer.max_steps=2",
                          "trainer.limit_val_batches=1", "trainer.progress_bar=false"])
    ckpt = train(cfg, data_root=tiny_root, out_dir=tmp_path / "run", device="cpu")["checkpoint"]
    outs, wall, cpu = infer_outputs(load_module(ckpt, "cpu"), str(tiny_root), 1)
    assert len(outs) == 2 and wall > 0 and cpu > 0
    got = registration_speed(outs, 0.12, max_validation=100)
    assert got["identical"] is True
    for k in ("before", "after", "before_cpu", "after_cpu"):
        assert list(got[k]) == list(N_POINTS) and all(v > 0 for v in got[k].values())


def test_ransac_lines_say_which_n_meet_the_target():
    from pcrcg.benchmarks.speed import ransac_lines

    rows = [{"n_points": 5000, "same_ours_s": 0.03, "same_ours_rr": 68.8, "same_open3d_s": 0.12, "same_open3d_rr": 72.9,
             "same_ours_cpu_s": 0.02, "same_open3d_cpu_s": 0.1},
            {"n_points": 500, "same_ours_s": 0.03, "same_ours_rr": 78.1, "same_open3d_s": 0.06, "same_open3d_rr": 76.0,
             "same_ours_cpu_s": 0.01, "same_open3d_cpu_s": 0.04}]
    lines = ransac_lines(rows)
    assert lines[2] == "| 5000 | 0.0300 (0.0200) | 68.8 | 0.1200 (0.1000) | 72.9 | 4.0x | met (>= 3x) | 5.0x | met |"
    assert lines[3].endswith("| 2.0x | missed (>= 3x) | 4.0x | met |")  # wall and CPU time can disagree


def test_evaluation_is_timed_at_one_thread_of_torch_and_of_the_native_pools(monkeypatch):
    """A run evaluates with torch and the native pools (OpenBLAS, OpenMP) at one thread; the benchmark left
    OpenBLAS at its default, which ran the new code's products on both cores (0.488 s of CPU for 0.265 s of wall
    per pair). Both evaluation benchmarks now time inside the run's limits."""
    import torch
    from threadpoolctl import threadpool_info

    from pcrcg.benchmarks import evaluation as ev

    seen = []

    def fake_registration_speed(outs, distance, *args):
        seen.append((torch.get_num_threads(), [p["num_threads"] for p in threadpool_info()]))
        return {}

    monkeypatch.setattr("pcrcg.models.train.load_module",
                        lambda ckpt, device: type("M", (), {"hparams": {"model": {"voxel_size": 0.06}}})())
    monkeypatch.setattr(ev, "infer_outputs", lambda module, root, pairs, *a: ([], 0.0, 0.0))
    monkeypatch.setattr(ev, "registration_speed", fake_registration_speed)
    got = speed.evaluation("model.ckpt", "data", 2)
    assert got["distance"] == pytest.approx(0.12) and seen
    torch_threads, pools = seen[0]
    assert torch_threads == 1 and pools and all(n == 1 for n in pools), seen


def test_the_registration_benchmark_refuses_negative_cores_before_any_work(monkeypatch):
    from pcrcg.benchmarks import registration
    from pcrcg.errors import ConfigError

    monkeypatch.setattr(registration, "make_pairs", lambda *a: pytest.fail("pairs built before the check"))
    with pytest.raises(ConfigError, match="--cores=-1"):
        registration.main(["--cores", "-1"])
