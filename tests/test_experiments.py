"""The tables' sweeps read from the experiment files (pcrcg.experiments) and the sweep scripts built on them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from pcrcg.errors import ConfigError
from pcrcg.experiments import TABLE_ORDER, experiment_jobs, main, sweep_axes

REPO = Path(__file__).resolve().parents[1]


def _experiment(tmp_path: Path, name: str, params: str) -> Path:
    (tmp_path / "experiment").mkdir(exist_ok=True)
    (tmp_path / "experiment" / f"{name}.yaml").write_text(
        f"# @package _global_\nexperiment_name: {name}\nhydra:\n  sweeper:\n    params:\n{params}")
    return tmp_path


def test_the_jobs_are_the_product_of_the_axes_in_their_order(tmp_path):
    conf = _experiment(tmp_path, "grid", "      features: rgb,deep\n      window_size: 3,7,11\n"
                                         "      profile.lifting.image_size: '[60,80]'\n")
    assert sweep_axes("grid", conf) == {"features": ["rgb", "deep"], "window_size": ["3", "7", "11"],
                                        "profile.lifting.image_size": ["[60,80]"]}
    jobs = experiment_jobs("grid", conf)
    assert len(jobs) == 6 and jobs[0] == ["features=rgb", "window_size=3", "profile.lifting.image_size=[60,80]"]
    assert jobs[-1][:2] == ["features=deep", "window_size=11"]
    assert experiment_jobs("single", _experiment(tmp_path, "single", "      {}\n")) == [[]]


def test_the_real_tables_sweeps(capsys):
    assert experiment_jobs("window_size") == [[f"window_size={w}"] for w in (3, 7, 11, 17)]
    assert sorted(experiment_jobs("main_results")) == [["features=deep"], ["features=none"]]
    assert main(["--jobs", "views"]) == 0
    assert capsys.readouterr().out.splitlines() == ["views views=1", "views views=2", "views views=3"]
    assert main(["--experiments"]) == 0
    assert tuple(capsys.readouterr().out.split()) == TABLE_ORDER
    for name in TABLE_ORDER:  # every table of the order has its experiment file
        assert experiment_jobs(name)
    # and every experiment file is in the order (all_tables.sh sweeps every table)
    assert sorted(p.stem for p in (REPO / "conf" / "experiment").glob("*.yaml")) == sorted(TABLE_ORDER)


def test_an_unknown_experiment_is_a_config_error_naming_it():
    with pytest.raises(ConfigError, match="experiment='nope'.*window_size"):
        sweep_axes("nope")


def test_the_two_lanes_script_deals_every_job_once():
    env = {**os.environ, "DRY_RUN": "1", "PYTHON": sys.executable, "SEEDS": "0,1"}
    out = subprocess.run(["bash", "sweeps/cpu_two_lanes.sh", "window_size", "views"], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    runs = [ln for ln in out.stdout.splitlines() if " -m pcrcg.run " in ln]
    assert len(runs) == 7 and all(ln.endswith(" -m") and "profile=cpu" in ln and "seed=0,1" in ln for ln in runs)
    jobs = sorted(ln.split("runtime.report_on_end=false seed=0,1 ")[1][:-3] for ln in runs)
    assert jobs == sorted([f"window_size={w}" for w in (3, 7, 11, 17)] + [f"views={v}" for v in (1, 2, 3)])
    lines = out.stdout.splitlines()
    assert lines[0] == "# queue: 2 lane(s), each takes the next job when it is free"
    order = [ln.split("seed=0,1 ")[1][:-3] for ln in runs]
    assert order == [f"window_size={w}" for w in (3, 7, 11, 17)] + [f"views={v}" for v in (1, 2, 3)]
    assert lines[-1].endswith("-m pcrcg.report profile=cpu")
    bad = subprocess.run(["bash", "sweeps/cpu_two_lanes.sh", "nope"], cwd=REPO, env=env, capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "nope" in bad.stderr


def test_one_lane_runs_every_job_in_order_and_a_bad_lane_count_stops_before_any_job():
    env = {**os.environ, "DRY_RUN": "1", "PYTHON": sys.executable, "LANES": "1"}
    out = subprocess.run(["bash", "sweeps/cpu_two_lanes.sh", "window_size", "views"], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "# queue: 1 lane(s), each takes the next job when it is free"
    jobs = [ln.split("runtime.report_on_end=false ")[1][:-3] for ln in lines if " -m pcrcg.run " in ln]
    assert jobs == [f"window_size={w}" for w in (3, 7, 11, 17)] + [f"views={v}" for v in (1, 2, 3)]
    for script in ("sweeps/cpu_two_lanes.sh", "sweeps/findings.sh"):
        bad = subprocess.run(["bash", script], cwd=REPO, env={**env, "LANES": "3"}, capture_output=True,
                             text=True, timeout=120)
        assert bad.returncode == 2 and "LANES=3" in bad.stderr, script
        assert " -m pcrcg." not in bad.stdout  # neither a job nor the report
    only = subprocess.run(["bash", "sweeps/cpu_two_lanes.sh", "window_size", "views"], cwd=REPO,
                          env={**env, "ONLY": "^views"}, capture_output=True, text=True, timeout=120)
    assert only.returncode == 0, only.stderr
    assert [ln.split("runtime.report_on_end=false ")[1][:-3] for ln in only.stdout.splitlines()
            if " -m pcrcg.run " in ln] == [f"views={v}" for v in (1, 2, 3)]
    none = subprocess.run(["bash", "sweeps/cpu_two_lanes.sh", "window_size"], cwd=REPO,
                          env={**env, "ONLY": "^views"}, capture_output=True, text=True, timeout=120)
    assert none.returncode == 2 and "ONLY=^views matches no job" in none.stderr and " -m pcrcg." not in none.stdout


def _lanes(tmp_path, body: str) -> subprocess.CompletedProcess:
    """sweeps/lib.sh's two_lanes in bash on a store and logs in ``tmp_path``, after ``body`` (the jobs, and the
    functions that stand in for the real ones)."""
    script = f"""set -u
. sweeps/lib.sh
LOGS={tmp_path}
MLFLOW_TRACKING_URI=sqlite:///{tmp_path}/m.db
PYTHON=true
{body}
two_lanes
"""
    return subprocess.run(["bash", "-c", script], cwd=REPO, capture_output=True, text=True, timeout=60)


def test_the_lanes_queue_gives_every_job_to_exactly_one_lane(tmp_path):
    """Two lanes at once take jobs from one queue (sweeps/lib.sh next_job): each job runs once, none is lost."""
    out = _lanes(tmp_path, f"""JOBS=(a b c d e f g h i j k)
job() {{ sleep 0.0$RANDOM; echo "$2" >>{tmp_path}/done; }}""")
    assert out.returncode == 0, out.stderr
    assert sorted((tmp_path / "done").read_text().split()) == list("abcdefghijk")
    assert not list(tmp_path.glob("queue.*"))


def test_a_lane_calls_the_scripts_after_job_hook_after_each_of_its_jobs(tmp_path):
    """sweeps/lib.sh lane: after each job, the script's `after_job <log> <job words...>` (findings.sh evaluates
    the job's experiment on the real scene while the checkpoint is still on the machine), right after that job
    and in the lane that ran it; none in a dry run."""
    body = f"""JOBS=("a x=1" "b x=2" "c x=3" "d x=4" "e x=5")
job() {{ echo "job $1 $2 $3" >>{tmp_path}/events; }}
after_job() {{ echo "after $1 $2 $3" >>{tmp_path}/events; }}"""
    out = _lanes(tmp_path, body)
    assert out.returncode == 0, out.stderr
    events = (tmp_path / "events").read_text().splitlines()
    assert len(events) == 10
    for lane in (f"{tmp_path}/lane1.log", f"{tmp_path}/lane2.log"):
        mine = [e.split(" ", 2)[::2] for e in events if e.split()[1] == lane]
        # each of the lane's jobs is followed by its hook, with the same log and words
        assert [w for w, _ in mine] == ["job", "after"] * (len(mine) // 2)
        assert [j for _, j in mine[0::2]] == [j for _, j in mine[1::2]]
    assert sorted(e.split(" ", 2)[2] for e in events if e.startswith("after")) == [
        "a x=1", "b x=2", "c x=3", "d x=4", "e x=5"]
    dry = _lanes(tmp_path, "DRY_RUN=1\n" + body)
    assert dry.returncode == 0, dry.stderr
    assert "after" not in dry.stdout


@pytest.mark.parametrize("job", [
    ["+experiment=icp_init", "method=icp", "icp_init=learned"],
    ["+experiment=icp_init", "method=color_icp", "icp_init=learned"],
    ["+experiment=ransac_budget", "features=deep", "registration=early_exit"],
    ["+experiment=ransac_budget", "features=deep", "registration=inlier_ranking"],
    ["+experiment=projection", "features=deep", "encoder2d=pri3d", "projection=explicit"],
    ["+experiment=window_size", "window_size=11"],
    ["+experiment=views_explicit", "views=2"],
    ["+experiment=backbone_2d", "encoder2d=pri3d", "encoder2d.training=detached"],
    ["+experiment=explicit_input", "projection.unseen_value=1.0", "matcher2d.pairs=paper"],
])
def test_the_tables_that_reuse_the_main_pcrcg_model_train_the_same_config(job):
    """icp_init's and ransac_budget's PCR-CG and the main rows of the explicit tables are main_results' PCR-CG
    (their files say so): the same training identity, so its checkpoint is reused, not another model trained
    (icp_init and ransac_budget once drew their windows around SIFT matches: another model)."""
    from pcrcg.config import load_run_config
    from pcrcg.pipeline import train_key

    def train_identity(overrides):  # the checkpoint cache's key, as a run computes it
        return train_key(load_run_config([*overrides, "profile=cpu"], validate=False))

    assert train_identity(job) == train_identity(["+experiment=main_results", "features=deep"])


def test_inlier_ranking_is_the_default_registration_ranked_by_inlier_correspondences():
    """registration=inlier_ranking changes the hypotheses' ranking and nothing else (the budget stays Open3D
    0.10's), and is the same run as the key it sets (a job written either way is skipped once it ran)."""
    from omegaconf import OmegaConf

    from pcrcg.config import load_run_config
    from pcrcg.pipeline import run_hash

    def cfg(*overrides):
        return load_run_config(["+experiment=ransac_budget", "features=none", *overrides, "profile=cpu"], validate=False)

    default, ranked = cfg("registration=default"), cfg("registration=inlier_ranking")
    a, b = OmegaConf.to_container(default.registration), OmegaConf.to_container(ranked.registration)
    assert (a["ransac"].pop("score"), b["ransac"].pop("score")) == ("overlap", "correspondences")
    assert a == b
    assert run_hash(ranked) == run_hash(cfg("registration=default", "registration.ransac.score=correspondences"))
    assert run_hash(ranked) != run_hash(default)


def test_the_views_table_two_view_row_is_the_projection_table_pri3d_implicit_model():
    """The paper's 2-view row is its Pri3D/implicit row: here the same training config, one checkpoint
    (the views table once left the unused matcher at SIFT: another model trained for the same numbers)."""
    from pcrcg.config import load_run_config
    from pcrcg.pipeline import train_key

    def key(overrides):
        return train_key(load_run_config([*overrides, "profile=cpu"], validate=False))

    implicit = key(["+experiment=projection", "features=deep", "encoder2d=pri3d", "projection=implicit"])
    assert key(["+experiment=views", "views=2"]) == implicit
    assert key(["+experiment=views", "views=1"]) != implicit


@pytest.mark.parametrize("job, same_as", [
    (["+experiment=ransac_budget", "features=none", "registration=default"], ["+experiment=main_results", "features=none"]),
    (["+experiment=ransac_budget", "features=deep", "registration=default"], ["+experiment=main_results", "features=deep"]),
    (["+experiment=projection", "features=deep", "encoder2d=pri3d", "projection=explicit"],
     ["+experiment=main_results", "features=deep"]),
    (["+experiment=window_size", "window_size=11"], ["+experiment=main_results", "features=deep"]),
    (["+experiment=backbone_2d", "encoder2d=pri3d", "encoder2d.training=detached"], ["+experiment=main_results", "features=deep"]),
    (["+experiment=views", "views=2"], ["+experiment=projection", "features=deep", "encoder2d=pri3d", "projection=implicit"]),
])
def test_rows_the_report_reads_from_another_experiment_are_the_same_run(job, same_as):
    """conf/report.yaml reads these rows from the other experiment's runs (ransac_budget's Open3D 0.10 rows are
    main_results' runs; the findings' deep/explicit, Pri3D, 11x11 and 2-view rows): training *and* evaluation
    config identical, only experiment_name differs (the run's identity, not only its checkpoint)."""
    from pcrcg.config import load_run_config
    from pcrcg.pipeline import run_hash

    def identity(overrides):
        return run_hash(load_run_config([*overrides, "profile=cpu"], validate=False))

    assert identity(job) == identity(same_as)
    assert identity(["+experiment=ransac_budget", "features=none", "registration=early_exit"]) != identity(
        ["+experiment=main_results", "features=none"])
