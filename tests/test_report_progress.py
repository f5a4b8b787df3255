"""python -m pcrcg.report.progress: what a relaunch of the findings sweep would skip and run, read from a store."""

from __future__ import annotations

import pytest

from test_run_support import FAKES, make_conf, run_cli

from pcrcg.report.progress import expand_jobs, job_states, render, sweeper_expansion, _store_runs


def test_open_sweeper_keys_expand_as_hydras_basic_sweeper_and_fixed_ones_do_not():
    params = {"method": "icp,color_icp", "icp_init": "identity, learned"}
    assert sweeper_expansion(["method=icp", "icp_init=learned"], params) == [["method=icp", "icp_init=learned"]]
    assert sweeper_expansion(["+method=icp"], params) == [["+method=icp", "icp_init=identity"],
                                                         ["+method=icp", "icp_init=learned"]]
    assert sweeper_expansion(["seed=0"], params) == [
        ["seed=0", "method=icp", "icp_init=identity"], ["seed=0", "method=icp", "icp_init=learned"],
        ["seed=0", "method=color_icp", "icp_init=identity"], ["seed=0", "method=color_icp", "icp_init=learned"]]
    assert sweeper_expansion(["seed=0"], None) == [["seed=0"]]


def test_a_finished_run_is_found_by_its_config_and_code_and_the_rest_is_estimated(tmp_path, monkeypatch):
    """One job of a sweep run at seed 0 (fake stages, a classical method: no training) is ``finished`` at this
    code, ``older code`` at another; seed 1 is ``to run`` with seed 0's wall time as its estimate; the seedless
    ICP from the identity is one run for every seed; a job never run has no estimate."""
    conf = make_conf(tmp_path / "conf")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    args = ["--config-path", str(conf), "+experiment=sift_dlt", "method=fpfh", "profile=tiny", *FAKES, "seed=0",
            f"hydra.sweep.dir={tmp_path}/multirun", "-m"]
    assert run_cli(args, tmp_path, monkeypatch) == 0
    jobs = [("sift_dlt", "method=fpfh"), ("icp_init", "method=icp icp_init=identity")]
    planned = expand_jobs(jobs, [0, 1], "tiny", config_dir=conf, extra=FAKES)
    assert [(e, s) for e, _, s, _ in planned] == [("sift_dlt", 0), ("icp_init", 0), ("sift_dlt", 1), ("icp_init", 1)]
    runs = _store_runs(uri, {"sift_dlt", "icp_init"})
    (run,) = runs["sift_dlt"]
    states = job_states(planned, runs, run["code"])
    assert [s.state for s in states] == ["finished", "to run", "to run", "same as #2"]
    assert states[0].run_id == run["id"] and states[0].seconds == pytest.approx(run["seconds"])
    assert states[2].seconds == pytest.approx(run["seconds"]) and states[1].seconds is None
    assert states[0].config_hash != states[2].config_hash  # the seed is part of FPFH's config
    assert [s.state for s in job_states(planned, runs, "another version")][0] == "older code"
    text = render(states, 2, run["code"], uri)
    assert "1 finished, 0 running, 0 stale, 0 older code, 2 to run, 1 same as" in text
    assert "Left: 2 runs" in text and "(1 without an estimate)" in text
    none_known = render(job_states(planned, {}, run["code"]), 2, run["code"], uri)  # an empty store: no estimate
    assert "Left: 3 runs, none with an estimate yet" in none_known and "--estimates-from URI" in none_known
    assert run["cpu"] is not None and states[0].cpu_seconds == pytest.approx(run["cpu"])
    assert "| CPU time |" in text and "CPU time: " in text and "(1 of the 1 finished runs logged it" in text
    assert "real scene" not in text.split("|---")[-1]  # no real data named: no line about it
    # the findings read sift_dlt on the real scene: the finished run has not been evaluated there yet
    real = job_states(planned, runs, run["code"], real="real-redkitchen", real_experiments=["sift_dlt"])
    assert [s.real for s in real] == ["no", "", "", ""]
    assert "Finished but not on the real scene: #1 " in render(real, 2, run["code"], uri)
    runs["sift_dlt"][0]["data"] = {"real-redkitchen"}
    seen = job_states(planned, runs, run["code"], real="real-redkitchen", real_experiments=["sift_dlt"])
    assert seen[0].real == "yes" and "not on the real scene" not in render(seen, 2, run["code"], uri)


def test_a_run_hashed_by_older_code_from_its_weights_files_bytes_is_found(tmp_path):
    """Code before aa220c7 digested a 2D weights file's bytes, this code its tensors: a sweep of such a version
    (``--code-version``) is read with both, so its finished runs are found; a run of other weights is not."""
    import torch
    from omegaconf import OmegaConf

    from pcrcg.pipeline import run_hash
    from pcrcg.tracking.hashing import to_plain

    w = tmp_path / "pri3d.pth"
    torch.save({"state_dict": {"w": torch.ones(3)}, "meta": {"created": "today"}}, w)
    cfg = OmegaConf.create({"experiment_name": "e", "seed": 0, "method": "sift_dlt", "encoder2d": {"weights": str(w)}})
    old, new = run_hash(to_plain(cfg), weights_by_bytes=True), run_hash(to_plain(cfg))
    assert old != new
    planned = [("e", ["x=1"], 0, cfg)]
    for h, want in ((old, "finished"), (new, "finished"), ("other weights", "to run")):
        store = {"e": [{"id": "r", "hash": h, "code": "c", "seconds": 5.0, "name": "x=1 seed=0",
                        "status": "FINISHED", "stale": False}]}
        assert job_states(planned, store, "c")[0].state == want, h


def test_a_running_run_whose_process_is_gone_is_stale():
    """RUNNING runs at this code: ``running`` while the owner lives, ``stale`` once it is gone (a relaunch runs
    the job again); a stale run beside a live one is ``running``; a finished one wins over both."""
    from omegaconf import OmegaConf

    from pcrcg.pipeline import run_hash
    from pcrcg.tracking.hashing import to_plain

    cfg = OmegaConf.create({"experiment_name": "e", "seed": 0, "x": 1})
    h = run_hash(to_plain(cfg))
    planned = [("e", ["x=1"], 0, cfg)]

    def state(*runs):
        store = {"e": [{"id": str(k), "hash": h, "code": "c", "seconds": 5.0, "name": "x=1", **r}
                       for k, r in enumerate(runs)]}
        return job_states(planned, store, "c")[0].state

    live = {"status": "RUNNING", "stale": False}
    dead = {"status": "RUNNING", "stale": True}
    assert state(live) == "running" and state(dead) == "stale" and state(dead, live) == "running"
    assert state(dead, {"status": "FINISHED", "stale": False}) == "finished"
    assert state({**dead, "code": "older"}) == "to run"


def test_a_missing_store_is_one_line(tmp_path, capsys):
    from pcrcg.report.progress import main

    assert main(["--tracking-uri", f"sqlite:///{tmp_path}/none.db", "--profile", "tiny"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("python -m pcrcg.report.progress: ") and "none.db" in err and "\n" not in err
