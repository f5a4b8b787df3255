"""Every row of the report selects runs that its experiment's sweep makes.

A table row (``conf/report.yaml``: ``specs.<table>.rows[].where`` and ``columns[].where``) and a finding's
selection (``findings``) filter the tracked runs by their flattened config and tags. A filter that no job
of the experiment satisfies would leave its cells empty forever ("no run of experiment ..."), however long
the sweep ran. Here each experiment's jobs (``pcrcg.experiments``) are composed as ``python -m pcrcg.run``
composes them, recorded as the tracker records them (``params.<key>``, tags ``label`` / ``method``), and
every filter must select at least one of them.
"""

from __future__ import annotations

from functools import lru_cache

import pandas as pd
import pytest
from omegaconf import OmegaConf

from pcrcg.config import CONF_DIR, load_run_config
from pcrcg.experiments import experiment_jobs
from pcrcg.pipeline import method_label
from pcrcg.report.findings import load_findings
from pcrcg.report.spec import parse_specs
from pcrcg.report.tables import _paper_value, fill_table, load_paper, match
from pcrcg.tracking.hashing import flatten, to_plain


def _record(experiment: str, overrides: list[str]) -> dict[str, str]:
    """What the store holds of one job: its params and the tags a table filters on (experiment
    ``default``: the main job, ``python -m pcrcg.run`` without an experiment file)."""
    exp = [] if experiment == "default" else [f"+experiment={experiment}"]
    cfg = load_run_config([*exp, *overrides, "profile=cpu"], validate=False)
    data = to_plain(cfg)
    rec = {f"params.{k}": v for k, v in flatten(data).items()}
    rec.update({"tags.label": method_label(data), "tags.method": str(data["method"]), "experiment": experiment})
    return rec


@lru_cache(maxsize=None)
def _jobs(experiment: str, extra: str | None = None) -> pd.DataFrame:
    """One row per job of the experiment's sweep; ``extra``: one job of its own (a row's ``job``) instead."""
    if extra is not None:
        return pd.DataFrame([_record(experiment, extra.split())])
    jobs = [[]] if experiment == "default" else experiment_jobs(experiment)
    return pd.DataFrame([_record(experiment, job) for job in jobs])


def _specs():
    raw = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "report.yaml").specs, resolve=True)
    return parse_specs(raw)


def test_jobs_are_recorded_with_the_params_and_tags_the_filters_read():
    runs = _jobs("window_size")
    assert len(runs) == 4 and set(runs["params.window_size"]) == {"3", "7", "11", "17"}
    assert set(runs["tags.label"]) == {"PCR-CG"}
    # the filter language: a value that no job has selects nothing, an unknown key selects nothing
    assert match(runs, {"window_size": 11}).sum() == 1 and not match(runs, {"window_size": 5}).any()
    assert not match(runs, {"no.such.key": 1}).any()
    # numbers as numbers: a float filter selects the text a float param is logged as, and a bool a logged True
    logged = pd.DataFrame({"params.x": ["1.0", "0.0", "1", "abc"], "params.b": ["True", "False", "true", "1"]})
    assert match(logged, {"x": 1.0}).tolist() == [True, False, True, False]
    assert match(logged, {"x": 0}).tolist() == [False, True, False, False]
    assert match(logged, {"x": "1.0"}).tolist() == [True, False, False, False]
    assert match(logged, {"b": True}).tolist() == [True, False, True, False]


@pytest.mark.parametrize("table", sorted(_specs()))
def test_every_row_and_cell_of_the_table_selects_a_job_of_its_experiment(table):
    """A row selects a job of its experiment's sweep, or the job it names; a cell for which the paper prints
    a number (columns with filters of their own) selects one too."""
    spec, paper = _specs()[table], load_paper()
    for row in spec.rows:
        if not row.where:  # a published baseline: not run here
            continue
        exp = row.experiment or spec.experiment
        runs = _jobs(exp, row.job)
        rows = match(runs, row.where)
        how = f"its job {row.job!r}" if row.job else "no job of the sweep"
        assert rows.any(), f"{table}: row {row.text!r} ({row.where}) selects {how} of experiment {exp!r}"
        if row.job:  # a job of its own: not one the sweep already runs
            assert not match(_jobs(exp), row.where).any(), f"{table}: row {row.text!r}: its job is in the sweep"
        for col in spec.columns:
            if col.where and _paper_value(paper, spec.paper_table, row, col) is not None:
                assert (rows & match(runs, col.where)).any(), \
                    f"{table}: row {row.text!r} x column {col.where} selects {how} of experiment {exp!r}"


def test_a_row_outside_the_sweep_says_how_to_run_it():
    spec = _specs()["backbone_2d"]
    disk = next(r for r in spec.rows if r.job)
    assert disk.command("backbone_2d", "cpu") == "python -m pcrcg.run +experiment=backbone_2d features=disk profile=cpu"
    filled = fill_table(spec, pd.DataFrame({"experiment": [], "status": []}), load_paper(), {"backbone_2d": "cpu"})
    reasons = {c.reason for c in filled.cells if c.row is disk}
    assert reasons == {"no run of experiment 'backbone_2d' with features.name=disk at profile cpu "
                       "(not in the sweep: python -m pcrcg.run +experiment=backbone_2d features=disk profile=cpu)"}
    assert _specs()["default"].rows[1].command("default") == "python -m pcrcg.run features=deep projection=explicit"


def test_every_finding_selects_the_job_that_sweeps_findings_sh_runs_for_it():
    spec = load_findings()
    assert spec is not None
    for finding in spec.claims:
        for sel in finding.rows:
            assert match(_jobs(sel.experiment, sel.job), sel.where).all(), \
                (finding.claim, sel.name, sel.job, dict(sel.where))
