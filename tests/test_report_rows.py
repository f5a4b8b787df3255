"""Every row of the report selects runs that its experiment's sweep makes.

A table row (``conf/report.yaml``: ``specs.<table>.rows[].where`` and ``columns[].where``) and a finding's
selection (``findings``) filter the tracked runs by their flattened config and tags. A filter that no job
of the experiment satisfies would leave its cells empty forever ("no run of experiment ..."), however long
the sweep ran. Here each experiment's jobs (``pcrcg.experiments``) are composed as ``python -m pcrcg.run``
composes them, recorded as the tracker records them (``params.<key>``, tags ``label`` / ``method``), and
every filter must select at least one of them. A row that counts another experiment's runs (``same_as``)
must name jobs of one config hash in both experiments.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from pcrcg.config import CONF_DIR, load_run_config
from pcrcg.experiments import experiment_jobs
from pcrcg.pipeline import method_label, run_hash
from pcrcg.report.findings import load_findings, parse_findings
from pcrcg.report.spec import default_where, parse_specs
from pcrcg.report.tables import _paper_value, fill_table, load_paper, match, paper_values
from pcrcg.tracking.hashing import flatten, to_plain


def _record(experiment: str, overrides: list[str]) -> dict[str, str]:
    """What the store holds of one job: its params and the tags a table filters on (experiment
    ``default``: the main job, ``python -m pcrcg.run`` without an experiment file)."""
    exp = [] if experiment == "default" else [f"+experiment={experiment}"]
    cfg = load_run_config([*exp, *overrides, "profile=cpu"], validate=False)
    data = to_plain(cfg)
    rec = {f"params.{k}": v for k, v in flatten(data).items()}
    rec.update({"tags.label": method_label(data), "tags.method": str(data["method"]), "experiment": experiment,
                "tags.config_hash": run_hash(cfg)})
    return rec


@lru_cache(maxsize=None)
def _jobs(experiment: str, extra: str | None = None) -> pd.DataFrame:
    """One row per job of the experiment's sweep; ``extra``: one job of its own (a row's ``job``) instead."""
    if extra is not None:
        return pd.DataFrame([_record(experiment, extra.split())])
    jobs = [[]] if experiment == "default" else experiment_jobs(experiment)
    return pd.DataFrame([_record(experiment, job) for job in jobs])


def _specs():
    cfg = OmegaConf.load(CONF_DIR / "report.yaml")
    return parse_specs(OmegaConf.to_container(cfg.specs, resolve=True),
                       default_where(OmegaConf.to_container(cfg.where, resolve=True)))


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
    spec, paper = _specs()[table], paper_values(load_paper())
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


@pytest.mark.parametrize("table", sorted(t for t, s in _specs().items() if any(r.same_as for r in s.rows)))
def test_a_row_that_counts_another_experiments_runs_names_the_same_config_there(table):
    """``same_as``: the other experiment's jobs that the row selects have the config hash of the row's own job,
    so that a run of either is the same run (a change to one experiment file that breaks this fails here)."""
    for row in (r for r in _specs()[table].rows if r.same_as):
        exp = row.experiment or _specs()[table].experiment
        own = _jobs(exp, row.job)
        own = own[match(own, row.where)]
        other = _jobs(row.same_as.experiment, row.same_as.job)
        other = other[match(other, {**row.where, **row.same_as.where})]
        assert len(own) == 1 and len(other) == 1, (table, row.text, len(own), len(other))
        assert own["tags.config_hash"].iloc[0] == other["tags.config_hash"].iloc[0], \
            f"{table}: row {row.text!r} is not the same config in {exp!r} and {row.same_as.experiment!r}"


def _fake_run(run_id: str, experiment: str, start: int, params: dict, rr: float) -> dict:
    return {"run_id": run_id, "experiment": experiment, "status": "FINISHED", "start_time": start,
            "tags.profile": "cpu", "tags.config_hash": "h", "tags.code_version": "c",
            **{f"params.{k}": str(v) for k, v in params.items()}, "metrics.3DLoMatch/rr_5000": rr}


def test_a_same_as_row_counts_the_other_experiments_runs_newest_per_seed_and_says_so():
    spec = parse_specs({"w": {"experiment": "window_size", "columns": [{"benchmark": "3DLoMatch", "metric": "RR",
                                                                        "n_points": 5000}],
                              "rows": [{"method": "PCR-CG", "variant": "11x11", "where": {"window_size": 11},
                                        "same_as": {"experiment": "main_results", "where": {"label": "PCR-CG"}}},
                                       {"method": "PCR-CG", "variant": "3x3", "where": {"window_size": 3}}]}})["w"]
    runs = pd.DataFrame([
        _fake_run("own0", "window_size", 5, {"window_size": 11, "seed": 0}, 10.0),
        _fake_run("old0", "main_results", 1, {"window_size": 11, "seed": 0}, 99.0),  # older than own0: not counted
        _fake_run("m1", "main_results", 2, {"window_size": 11, "seed": 1}, 20.0),
        _fake_run("pred", "main_results", 3, {"window_size": 11, "seed": 2}, 50.0),  # Predator: not the row's config
        _fake_run("w3", "window_size", 4, {"window_size": 3, "seed": 0}, 7.0),
    ])
    runs["tags.label"] = ["PCR-CG", "PCR-CG", "PCR-CG", "Predator", "PCR-CG"]
    filled = fill_table(spec, runs, load_paper(), {"window_size": "cpu", "main_results": "cpu"})
    eleven, three = (filled.cell(r, spec.columns[0]) for r in spec.rows)
    assert sorted(r.run_id for r in eleven.runs) == ["m1", "own0"] and eleven.mean == 15.0
    assert [r.run_id for r in three.runs] == ["w3"]  # a row without same_as: its own experiment only
    assert filled.shared == ["PCR-CG 11x11: also the runs of experiment 'main_results' (label=PCR-CG) (2 finished), "
                             "the same config"]
    from pcrcg.report.render import to_markdown

    assert "Rows that count another experiment's runs of their config: PCR-CG 11x11" in to_markdown(filled)
    # neither experiment ran it: the reason names both
    empty = fill_table(spec, runs[runs["run_id"] == "w3"], load_paper(), {"window_size": "cpu", "main_results": "cpu"})
    assert empty.cell(spec.rows[0], spec.columns[0]).reason == (
        "no run of experiment 'window_size' with window_size=11 at profile cpu; "
        "nor of experiment 'main_results' (label=PCR-CG)")


@pytest.mark.parametrize("bad", [{"where": {"label": "x"}}, {"experiment": 3}, {"experiment": "m", "wher": {}}, "m"])
def test_a_bad_same_as_is_one_line_naming_the_setting(bad):
    from pcrcg.errors import ConfigError

    with pytest.raises(ConfigError, match=r"specs\.w\.rows\[0\]\.same_as"):
        parse_specs({"w": {"columns": [{"benchmark": "3DLoMatch", "metric": "RR"}],
                           "rows": [{"method": "PCR-CG", "where": {"a": 1}, "same_as": bad}]}})


def test_a_row_outside_the_sweep_says_how_to_run_it():
    spec = _specs()["backbone_2d"]
    disk = next(r for r in spec.rows if r.job)
    assert disk.command("backbone_2d", "cpu") == "python -m pcrcg.run +experiment=backbone_2d features=disk profile=cpu"
    filled = fill_table(spec, pd.DataFrame({"experiment": [], "status": []}), load_paper(), {"backbone_2d": "cpu"})
    reasons = {c.reason for c in filled.cells if c.row is disk}
    assert reasons == {"no run of experiment 'backbone_2d' with features.name=disk, registration.ransac.score=overlap "
                       "at profile cpu "
                       "(not in the sweep: python -m pcrcg.run +experiment=backbone_2d features=disk profile=cpu)"}
    assert _specs()["default"].rows[1].command("default") == "python -m pcrcg.run features=deep projection=explicit"


def test_every_finding_selects_the_job_that_sweeps_findings_sh_runs_for_it():
    spec = load_findings()
    assert spec is not None
    for finding in spec.claims:
        for sel in finding.rows:
            assert match(_jobs(sel.experiment, sel.job), sel.where).all(), \
                (finding.claim, sel.name, sel.job, dict(sel.where))


class _FakeSource:
    """Per-pair outcomes by run id (index (scene, i, j)), as pcrcg.report.outcomes.OutcomeSource gives them."""

    def __init__(self, vectors: dict[str, np.ndarray]):
        self.vectors = vectors

    def outcomes(self, run_id, key, logged):
        from pcrcg.report.outcomes import Outcomes

        v = self.vectors[run_id]
        idx = pd.MultiIndex.from_arrays([["s0"] * len(v), list(range(len(v))), list(range(1, len(v) + 1))],
                                        names=("scene", "i", "j"))
        return Outcomes(pd.Series(v, index=idx), source="fake")


def test_a_run_that_reads_no_seed_is_compared_with_every_seed_of_the_other_row():
    """ICP from the identity ran once (seed 0, or a run before the seed_independent tag: its params say so);
    ICP from the learned estimate ran seeds 0 and 1: both seeds are compared, seed against that one run."""
    from pcrcg.report.orderings import StatsSettings, check_orderings

    spec = parse_specs({"icp": {"experiment": "icp_init", "columns": [{"benchmark": "3DLoMatch", "metric": "RR"}],
                                "rows": [{"method": "ICP", "variant": "identity", "where": {"icp_init": "identity"}},
                                         {"method": "ICP", "variant": "learned", "where": {"icp_init": "learned"}}],
                                "compare": {"pairs": [["ICP identity", "ICP learned"]]}}})["icp"]
    rng = np.random.default_rng(0)
    base = (rng.random(300) < 0.1).astype(float)
    vec = {"id0": base, "l0": np.maximum(base, rng.random(300) < 0.3), "l1": np.maximum(base, rng.random(300) < 0.2)}
    rows = []
    for rid, init, seed, start in (("id0", "identity", 0, 1), ("l0", "learned", 0, 2), ("l1", "learned", 1, 3)):
        rows.append({"run_id": rid, "experiment": "icp_init", "status": "FINISHED", "start_time": start,
                     "tags.profile": "cpu", "tags.config_hash": rid, "tags.code_version": "c", "params.method": "icp",
                     "params.icp_init": init, "params.seed": str(seed), "metrics.3DLoMatch/rr": 100 * vec[rid].mean()})
    filled = fill_table(spec, pd.DataFrame(rows), load_paper(), {"icp_init": "cpu"})
    assert filled.cell(spec.rows[0], spec.columns[0]).runs[0].seedless
    assert not filled.cell(spec.rows[1], spec.columns[0]).runs[0].seedless
    filled.orderings = check_orderings(filled, _FakeSource(vec), StatsSettings(), keep_empty=True)
    (line,) = filled.orderings
    assert line.n_seeds == 2 and line.ref_runs == ["id0"] and line.row_runs == ["l0", "l1"]
    assert line.interval.seed_mode == "resample" and line.interval.n_seeds == 2
    expected = 100 * np.mean([vec["l0"].mean() - base.mean(), vec["l1"].mean() - base.mean()])
    assert line.ours_diff == pytest.approx(expected) and line.interval.lo > 0
    assert line.ours_std == pytest.approx(100 * abs(vec["l0"].mean() - vec["l1"].mean()) / np.sqrt(2))


def test_a_table_names_each_experiment_it_reads_once():
    """main_results reads projection twice (two rows) and ransac_budget main_results twice (same_as): once each."""
    specs = _specs()
    for name, spec in specs.items():
        assert len(spec.experiments) == len(set(spec.experiments)), (name, spec.experiments)
        assert spec.experiments[0] == spec.experiment
    assert specs["main_results"].experiments == ["main_results", "projection"]
    assert specs["ransac_budget"].experiments == ["ransac_budget", "main_results"]


def test_the_report_where_is_inherited_by_every_row_of_ours_and_a_row_s_own_value_wins():
    from pcrcg.errors import ConfigError

    defaults = default_where({"registration": {"ransac": {"score": "overlap"}}, "profile": {"name": "cpu"}})
    assert defaults == {"registration.ransac.score": "overlap", "profile.name": "cpu"}
    assert default_where(None) == {} and default_where({}) == {}
    with pytest.raises(ConfigError, match="where"):
        default_where(["registration.ransac.score=overlap"])  # type: ignore[arg-type]
    spec = parse_specs({"t": {"experiment": "ransac_budget", "columns": [{"benchmark": "3DLoMatch", "metric": "RR"}],
                              "rows": [{"method": "FCGF", "reason": "published"},
                                       {"method": "Predator", "where": {"label": "Predator"}},
                                       {"method": "Predator", "variant": "inlier", "where": {
                                           "label": "Predator", "registration.ransac.score": "correspondences"}}]}},
                       {"registration.ransac.score": "overlap"})["t"]
    baseline, overlap, inlier = spec.rows
    assert baseline.where == {}  # a published baseline: no runs of ours, with or without the report's filters
    assert overlap.where == {"label": "Predator", "registration.ransac.score": "overlap"}
    assert inlier.where == {"label": "Predator", "registration.ransac.score": "correspondences"}
    runs = pd.DataFrame({"params.registration.ransac.score": ["overlap", "correspondences"],
                         "tags.label": ["Predator", "Predator"]})
    assert match(runs, overlap.where).tolist() == [True, False]
    assert match(runs, inlier.where).tolist() == [False, True]


@pytest.mark.parametrize("registration", ["inlier_ranking", "early_exit"])
def test_a_findings_sweep_with_another_registration_runs_jobs_that_its_report_selects(registration):
    """``REGISTRATION=<group> sweeps/findings.sh``: the report overrides that `--report-overrides` prints make the
    findings of the runs so registered; every row that sets no registration filter of its own then runs its job
    with the group and selects that job (not the paper's protocol's); a row that sets one keeps its job."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from pcrcg.report.findings import registration_of, registration_overrides, registration_where

    overrides = registration_overrides(registration)
    assert overrides and all(o.startswith("++where.registration.") for o in overrides)
    if registration == "inlier_ranking":
        assert overrides == ["++where.registration.ransac.score='correspondences'"]
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR.resolve()), version_base="1.3"):
        cfg = compose(config_name="report", overrides=overrides)
    GlobalHydra.instance().clear()
    defaults = default_where(OmegaConf.to_container(cfg.where, resolve=True))
    assert registration_of(defaults) == registration and registration_of(default_where(
        OmegaConf.to_container(OmegaConf.load(CONF_DIR / "report.yaml").where))) is None
    plain = load_findings()
    spec = parse_findings(OmegaConf.to_container(OmegaConf.load(CONF_DIR / "report.yaml").findings, resolve=True),
                          defaults)
    assert plain is not None and spec is not None
    assert spec.jobs() == load_findings(where=registration_where(registration)).jobs()  # the sweep's job list
    for plain_finding, finding in zip(plain.all, spec.all):
        for before, sel in zip(plain_finding.rows, finding.rows):
            if before.where.get("registration.ransac.score") != "overlap" or "registration=" in before.job:
                assert sel.job == before.job, (finding.claim, sel.name)  # a row about the ranking keeps its job
                continue
            own = [t for t in before.job.split() if not t.startswith(("registration=", "registration."))]
            assert sel.job == " ".join([*own, f"registration={registration}"])
            assert match(_jobs(sel.experiment, sel.job), sel.where).all(), (finding.claim, sel.name, sel.job)
            assert not match(_jobs(sel.experiment, before.job), sel.where).any(), (finding.claim, sel.name)
    assert all(s.job.split().count(f"registration={registration}") == 1 for f in spec.claims for s in f.rows)
    with pytest.raises(Exception, match="registration"):
        registration_where("no_such_group")
