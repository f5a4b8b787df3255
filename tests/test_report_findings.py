"""The findings table (reports/findings.*): verdicts from paired intervals, seeds, the real scene, the sweep's jobs."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from pcrcg.config import CONF_DIR
from pcrcg.errors import ConfigError
from pcrcg.evaluation.pairs import PAIR_COLUMNS
from pcrcg.report import generate_report
from pcrcg.report.findings import (DASH, HOLDS, NOT_RESOLVED, NOT_RUN, REVERSED, line_verdict, load_findings, ours_text,
                                   paper_position, parse_findings)
from pcrcg.report.outcomes import split_prefix
from pcrcg.report.stats import recall

ROOT = Path(__file__).resolve().parents[1]
N = (5000, 2500, 1000, 500, 250)
SCENES = {"kitchen": 24, "office": 16}  # counted pairs per scene of the generated 3DLoMatch
REAL = {"redkitchen": 10}  # the real scene: few pairs
PREFIX = "real-redkitchen"


def _cfg(out_dir: Path, uri: str, **extra) -> dict:
    raw = OmegaConf.load(CONF_DIR / "report.yaml")
    for key in ("hydra", "defaults"):
        raw.pop(key, None)
    cfg = OmegaConf.to_container(raw, resolve=True)
    cfg.update(out_dir=str(out_dir), tracking_uri=uri, tables=["window_size"], profile="cpu", **extra)
    return cfg


def _pairs_csv(path: Path, ok: dict[str, np.ndarray], sizes=N) -> float:
    """Write a per-pair file in the evaluation's format (every pair counted, the same outcome at every N of
    ``sizes``; ``(None,)``: one estimate per pair, as FPFH's); returns the protocol's recall of these outcomes."""
    rows = [{"scene": s, "i": k, "j": k + 2, "n_points": "" if n is None else n, "counted": 1, "present": 1,
             "registered": int(v), "error": "", "rre": "", "rte": "", "inlier_ratio": ""}
            for n in sizes for s, vals in ok.items() for k, v in enumerate(vals)]
    path.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows, columns=list(PAIR_COLUMNS)).to_csv(path, index=False)
    return recall(np.concatenate(list(ok.values())).astype(float), [s for s, v in ok.items() for _ in v])


def _run(tr, work: Path, name: str, params: dict, tags: dict, ok: dict, real_ok: dict | None = None,
         bench: str = "3DLoMatch", sizes=N) -> str:
    """A FINISHED run registering the pairs ``ok`` (``bench``, every N of ``sizes``; ``(None,)``: its one
    estimate, ``<bench>/rr``), and ``real_ok`` on the real scene."""
    folder = work / name.replace(" ", "_").replace("=", "-")
    rr = _pairs_csv(folder / "pairs" / f"{bench}.csv", ok, sizes)
    metrics = {f"{bench}/rr" if n is None else f"{bench}/rr_{n}": rr for n in sizes}
    if real_ok is not None:
        rr = _pairs_csv(folder / PREFIX / "pairs" / "3DLoMatch.csv", real_ok)
        metrics.update({f"{PREFIX}/3DLoMatch/rr_{n}": rr for n in N})
    rid = tr.start(name, {"experiment": tr.experiment_name, "git_sha": "d" * 40, "code_version": "v1",
                          "profile": "cpu", "config_hash": name, **tags})
    tr.log_params(rid, {"registration.ransac.score": "overlap", **params})  # the report's default where
    tr.log_metrics(rid, metrics)
    tr.log_artifact(rid, folder / "pairs", "pairs")
    if real_ok is not None:
        tr.log_artifact(rid, folder / PREFIX / "pairs", f"{PREFIX}/pairs")
    tr.finish(rid)
    return rid


def _base(rng, scenes: dict[str, int], p: float) -> dict[str, np.ndarray]:
    return {s: rng.random(n) < p for s, n in scenes.items()}


def _more(rng, ok: dict[str, np.ndarray], frac: float) -> dict[str, np.ndarray]:
    """Every pair ``ok`` registers and ``frac`` of each scene's pairs more."""
    out = {}
    for s, v in ok.items():
        free = np.flatnonzero(~v)
        out[s] = v.copy()
        out[s][rng.choice(free, size=min(len(free), int(round(frac * len(v)))), replace=False)] = True
    return out


def _store(root: Path, flip: bool = False) -> str:
    """main_results (3 seeds, real scene too), window_size (3 seeds), views and projection (one seed) runs.

    PCR-CG = Predator + 35-45% of the pairs (``flip``: the other way round); it is also the 11x11 row
    (conf/report.yaml reads main_results' PCR-CG there): 3x3 = Predator, 7x7 = PCR-CG (no difference),
    17x17 = PCR-CG + 35%. 1 view = 2 views (the projection table's Pri3D/implicit run). No other projection runs."""
    from pcrcg.tracking.tracker import RunTracker
    from pcrcg.tracking.store import ensure_store

    uri = f"sqlite:///{root}/mlflow.db"
    ensure_store(uri)
    rng = np.random.default_rng(5)
    work = root / "work"
    main, windows = RunTracker(uri, "main_results"), RunTracker(uri, "window_size")
    for seed in (0, 1, 2):
        weak, weak_real = _base(rng, SCENES, 0.3), _base(rng, REAL, 0.1)
        strong, strong_real = _more(rng, weak, 0.35 + 0.05 * seed), _more(rng, weak_real, 0.7)
        if flip:
            weak, strong, weak_real, strong_real = strong, weak, strong_real, weak_real
        for label, ok, real in (("Predator", weak, weak_real), ("PCR-CG", strong, strong_real)):
            _run(main, work, f"{label} seed={seed}", {"seed": seed, "encoder2d.name": "pri3d"}, {"label": label}, ok, real)
        for ws, ok in ((3, weak), (7, strong), (17, _more(rng, strong, 0.35))):
            _run(windows, work, f"window_size={ws} seed={seed}", {"window_size": ws, "seed": seed, "encoder2d.name": "pri3d"},
                 {"label": "PCR-CG"}, ok)
    w3 = _base(rng, SCENES, 0.3)
    implicit = {"seed": 0, "projection.name": "implicit", "encoder2d.name": "pri3d"}
    _run(RunTracker(uri, "views"), work, "views=1", {"views": 1, **implicit}, {"label": "PCR-CG"}, w3)
    _run(RunTracker(uri, "projection"), work, "deep/implicit", {"features.name": "deep", **implicit}, {"label": "PCR-CG"}, w3)
    return uri


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("findings")
    uri = _store(root)
    out = root / "reports"
    result = generate_report(_cfg(out, uri), base_dir=root, command="python -m pcrcg.report")
    return {"root": root, "out": out, "result": result, "uri": uri}


def _lines(report, number: int, comparison: str | None = None, at=5000):
    f = report["result"].findings
    return [ln for ln in f.lines if ln.finding.number == number and not ln.finding.is_target and ln.ours.at == at
            and (comparison is None or ln.comparison == comparison)]


def _claim(report, number: int, real: bool = False):
    f = report["result"].findings
    return f.claim_verdict(f.spec.claims[number - 1], real=real)


def test_the_spec_has_the_papers_eight_claims_and_their_differences():
    spec = load_findings()
    assert len(spec.claims) == 8 and spec.real == PREFIX and spec.seeds == (0, 1, 2)
    assert [len(f.compare) for f in spec.claims] == [1, 1, 2, 1, 2, 3, 1, 2]
    assert {s.experiment for f in spec.claims for s in f.rows} == {
        "main_results", "projection", "views", "backbone_2d", "window_size", "geotransformer", "icp_init"}
    # main_results' PCR-CG is also the deep/explicit (2, 3), Pri3D (5) and 11x11 (6) rows; the projection table's
    # Pri3D/implicit row is also the 2-view row (4): each job once
    assert ("main_results", "features=deep") in spec.jobs()
    assert ("projection", "features=deep encoder2d=pri3d projection=explicit") not in spec.jobs()
    assert ("views", "views=2") not in spec.jobs()
    # 17 for the claims; FPFH + RANSAC for the targets, and both with RANSAC ranking by inlier correspondences
    assert len(spec.jobs()) == len(set(spec.jobs())) == 20
    assert spec.jobs()[-3:] == [("sift_dlt", "method=fpfh"), ("sift_dlt", "method=fpfh registration=inlier_ranking"),
                                ("ransac_budget", "features=none registration=inlier_ranking")]
    overlap, inlier = spec.targets[:3], spec.targets[3:]
    target, *real = overlap
    assert target.margin == 10 and target.benchmark == "3DMatch" and target.label == "T1"
    assert [s.single for s in target.rows] == [True, False]
    # issue 20's: the same rows on the real scene's benchmarks, so FPFH's runs are evaluated there too
    assert [t.benchmark for t in real] == [f"{PREFIX}/3DMatch", f"{PREFIX}/3DLoMatch"] and all(t.margin == 0 for t in real)
    # T4-T6: T1-T3 with both rows' RANSAC ranking its hypotheses by inlier correspondences
    assert [(t.label, t.benchmark, t.margin) for t in inlier] == [(f"T{k + 4}", t.benchmark, t.margin) for k, t in enumerate(overlap)]
    for t in inlier:
        assert all(s.where["registration.ransac.score"] == "correspondences" for s in t.rows)
    assert all(t.rows[0].where["registration.ransac.score"] == "overlap" for t in overlap)  # not the other FPFH runs
    assert spec.real_experiments[-2:] == ["sift_dlt", "ransac_budget"]


def test_pcrcg_above_predator_holds_with_seeds_as_mean_and_std(report):
    [line] = _lines(report, 1)
    assert line.verdict == HOLDS and line.ours.interval.lo > 0
    assert line.ours.paper_diff == pytest.approx(66.3 - 59.8)  # the paper's +6.5 at 5000 points
    assert line.ours.n_seeds == 3 and line.ours.ours_std > 0
    assert line.ours.interval.n_pairs == sum(SCENES.values())
    assert _claim(report, 1) == HOLDS
    [mean] = _lines(report, 1, at="mean")
    assert mean.verdict == HOLDS and mean.where == "3DLoMatch RR mean over N"
    md = (report["out"] / "findings.md").read_text()
    assert ("| 1. PCR-CG (explicit, deep, Pri3D, 2 views) > Predator on 3DLoMatch | PCR-CG − Predator "
            "| 3DLoMatch RR 5000 | +6.5 | +") in md
    assert " (3 seeds) | [+" in md
    assert "| Paper Δ vs interval |" in md and "*within*" in md
    assert f"] | {paper_position(line.ours)} | holds |" in md


def test_the_real_scene_column_reads_the_prefixed_metrics_and_artifacts(report):
    [line] = _lines(report, 1)
    assert line.real is not None and line.real.interval is not None
    assert line.real.interval.n_pairs == 10 and line.real.interval.n_scenes == 1
    assert line.real_verdict == HOLDS and line.real.source == f"the run's {PREFIX} pairs artifact"
    assert _claim(report, 1, real=True) == HOLDS
    # runs that were not evaluated on the real scene: a dash, and the command that does it
    [win] = _lines(report, 6, "11x11 − 3x3")
    assert win.verdict == HOLDS and win.real_verdict is None and "mode=tracked" in win.real_note
    md = (report["out"] / "findings.md").read_text()
    assert f"{PREFIX} verdict |" in md and "— [" in md
    assert split_prefix(f"{PREFIX}/3DLoMatch/rr_5000") == (PREFIX, "3DLoMatch/rr_5000")
    assert split_prefix("3DLoMatch/rr_5000") == (None, "3DLoMatch/rr_5000")


def test_a_window_holds_one_is_not_resolved_one_is_reversed(report):
    assert _lines(report, 6, "11x11 − 3x3")[0].verdict == HOLDS
    same = _lines(report, 6, "11x11 − 7x7")[0]
    assert same.verdict == NOT_RESOLVED and same.ours.interval.lo <= 0 <= same.ours.interval.hi
    rev = _lines(report, 6, "11x11 − 17x17")[0]
    assert rev.verdict == REVERSED and rev.ours.interval.hi < 0 and rev.ours.paper_diff == pytest.approx(2.2)
    assert _claim(report, 6) == REVERSED  # 11x11 is not the best of the four
    assert _lines(report, 4)[0].verdict == NOT_RESOLVED and _claim(report, 4) == NOT_RESOLVED


def test_a_finding_without_runs_is_not_run_and_says_which_and_how(report):
    line = _lines(report, 3, "deep/explicit − SIFT/explicit")[0]
    assert line.verdict == NOT_RUN and line.ours.interval is None
    assert "no run of experiment 'projection'" in line.note and "features.name=sift" in line.note
    assert ("python -m pcrcg.run +experiment=projection features=sift projection=explicit "
            "profile=cpu seed=0,1,2 -m") in line.note
    assert _claim(report, 3) == NOT_RUN and _claim(report, 3, real=True) == NOT_RUN
    md = (report["out"] / "findings.md").read_text()
    assert "| 3 | deep > SIFT > RGB lifted features under the same (explicit) projection | not run | not run |" in md


def test_a_row_reads_another_experiments_runs_of_the_same_config(report):
    """Finding 2's deep/explicit row is main_results' PCR-CG (seeds 0-2); its implicit row the projection run
    (seed 0). The line compares the seed both ran, seed 0 with seed 0: pooling the explicit row's seeds 1-2
    against nothing would mix seed effects into the difference. Rows of the same seeds keep them all (claim 1)."""
    [line] = _lines(report, 2)
    assert line.verdict == HOLDS and len(line.ours.row_runs) == 1 and len(line.ours.ref_runs) == 1
    assert len(_lines(report, 1)[0].ours.row_runs) == 3
    assert line.reference.experiment == "projection" and line.compared.experiment == "main_results"


def test_files_index_and_code_versions(report):
    out = report["out"]
    df = pd.read_csv(out / "findings.csv", dtype={"finding": str})
    assert set(df["finding"]) == {str(k) for k in range(1, 9)} | {f"T{k}" for k in range(1, 7)}
    assert set(df.loc[df["finding"].str.startswith("T"), "verdict"]) == {NOT_RUN}  # no 3DMatch runs, no FPFH
    row = df[(df["finding"] == "1") & (df["at"] == "5000")].iloc[0]
    assert row["verdict"] == HOLDS and row["n_seeds"] == 3 and row["ci_low"] > 0 and row["real_verdict"] == HOLDS
    assert row["ci_seeds"] == "resample (3)"
    by_seed = dict(kv.split(":") for kv in row["ours_by_seed"].split(";"))
    assert list(by_seed) == ["0", "1", "2"]  # seed against seed, in seed order; their mean is ours
    assert np.mean([float(v) for v in by_seed.values()]) == pytest.approx(row["ours_diff"], abs=0.06)
    assert row["claim_verdict"] == HOLDS and row["code_versions"] == "v1"
    assert len(row["compared_run_ids"].split(";")) == 3
    md = (out / "findings.md").read_text()
    assert "code versions behind the findings: v1 (17 runs)" in md  # 6 main_results, 9 windows, views, projection
    assert "identity=config_and_code" in md
    index = (out / "README.md").read_text()
    assert "## The paper's findings, tested ([md](findings.md)" in index
    assert (out / "findings.png").stat().st_size > 10_000 and "](findings.png)" in md  # the forest plot
    assert "](findings.png)" in index
    tex = (out / "findings.tex").read_text()
    assert r"PCR-CG $-$ Predator & 3DLoMatch RR 5000" in tex


def test_the_verdicts_flip_with_the_outcomes(report, tmp_path):
    uri = _store(tmp_path, flip=True)
    result = generate_report(_cfg(tmp_path / "reports", uri), base_dir=tmp_path)
    flipped = result.findings.claim_verdict(result.findings.spec.claims[0])
    assert flipped == REVERSED and _claim(report, 1) == HOLDS
    real = result.findings.claim_verdict(result.findings.spec.claims[0], real=True)
    assert real == REVERSED


def test_findings_can_be_left_out_and_bad_specs_name_the_setting(report, tmp_path):
    result = generate_report(_cfg(tmp_path / "none", report["uri"], findings=None), base_dir=report["root"])
    assert result.findings is None and not (tmp_path / "none" / "findings.md").exists()
    spec = _cfg(tmp_path, report["uri"])["findings"]  # without the real scene (nor the targets on it)
    no_real = generate_report(_cfg(tmp_path / "noreal", report["uri"], findings={
        **spec, "real": None, "targets": spec["targets"][:1]}), base_dir=report["root"])
    assert no_real.findings.lines[0].real is None and PREFIX not in (tmp_path / "noreal" / "findings.md").read_text()
    raw = _cfg(tmp_path, report["uri"])["findings"]
    raw["claims"][0]["compare"] = [["Predator", "nobody"]]
    with pytest.raises(ConfigError, match=r"findings.claims\[0\].compare"):
        parse_findings(raw)


def test_what_differs_from_the_paper_is_said_where_a_claim_is_reversed_or_not_resolved(report, tmp_path):
    """``findings.claims[].differs``: a paragraph under the findings for each claim that is reversed (6 here) or not
    resolved (4), none for a claim that holds (1, 2) or is not run (3); a bad value names the setting."""
    spec = report["result"].findings.spec
    assert all(f.differs for f in spec.claims[:7]) and spec.claims[7].differs is None  # conf/report.yaml's
    md = (report["out"] / "findings.md").read_text()
    section = md.split("### Where our setting differs from the paper's", 1)[1].split("\n#", 1)[0]
    said = [f.number for f in spec.claims if f"**{f.number}. {f.claim}**" in section]
    assert said == [4, 6], said
    assert f"**6. {spec.claims[5].claim}** (reversed): {spec.claims[5].differs}" in section  # no real-scene runs of it
    assert "\n" not in spec.claims[5].differs and "  " not in spec.claims[5].differs  # the YAML's lines joined
    raw = _cfg(tmp_path, report["uri"])["findings"]
    raw["claims"][0]["differs"] = 5
    with pytest.raises(ConfigError, match=r"findings.claims\[0\].differs"):
        parse_findings(raw)


def test_the_sweep_runs_every_rows_job_with_every_seed(tmp_path):
    env = {**os.environ, "DRY_RUN": "1", "PYTHON": str(ROOT / ".venv" / "bin" / "python"), "SHARED": str(tmp_path),
           "REAL_ROOT": str(tmp_path / "real"), "LOGS": str(tmp_path / "logs")}
    out = subprocess.run(["bash", "sweeps/findings.sh"], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=120, check=True).stdout
    runs = [ln for ln in out.splitlines() if " -m pcrcg.run " in ln]
    spec = load_findings()
    for f in spec.all:  # the claims' rows and the targets' (FPFH + RANSAC)
        for s in f.rows:
            for seed in (0, 1, 2):
                want = f"+experiment={s.experiment} profile=cpu runtime.report_on_end=false {s.job} seed={seed} -m"
                assert sum(ln.endswith(want) for ln in runs) == 1, (f.claim, s.name, seed)
    assert len(runs) == 3 * len(spec.jobs())
    seeds = [int(ln.split(" seed=")[1][:-3]) for ln in runs]
    assert seeds == sorted(seeds)  # seed by seed: every job of seed 0 before any of seed 1
    assert f"-m pcrcg.prepare data=threedmatch data.source.fragments_dir={tmp_path}/real-3dmatch-fragments" in out
    evals = [ln for ln in out.splitlines() if "-m pcrcg.evaluate mode=tracked" in ln]
    assert [ln.split("experiments=[")[1].split("]")[0] for ln in evals] == [
        "main_results", "projection", "views", "backbone_2d", "window_size", "geotransformer", "icp_init", "sift_dlt",
        "ransac_budget"]
    assert all("name=real-redkitchen" in ln for ln in evals)  # sift_dlt, ransac_budget: the real-scene targets
    only = subprocess.run(["bash", "sweeps/findings.sh"], cwd=ROOT, env={**env, "ONLY": "^main_results"},
                          capture_output=True, text=True, timeout=120, check=True).stdout
    assert [ln.split("experiments=[")[1].split("]")[0] for ln in only.splitlines()
            if "-m pcrcg.evaluate mode=tracked" in ln] == ["main_results"]  # not the experiments it did not run
    assert only.strip().splitlines()[-1].endswith("tables=[main_results] out_dir=reports/findings-cpu")
    assert out.strip().splitlines()[-1].endswith(
        "-m pcrcg.report profile=cpu tables=[main_results,projection,views,backbone_2d,window_size,geotransformer,"
        "icp_init,sift_dlt,ransac_budget] out_dir=reports/findings-cpu")
    assert not (tmp_path / "logs").exists()  # a dry run writes nothing


def test_line_verdicts_follow_the_expected_sign_and_need_both_rows():
    from pcrcg.report.orderings import OrderingLine
    from pcrcg.report.spec import Comparison, Row
    from pcrcg.report.stats import Interval

    a, b = Row("A", where={"x": 1}), Row("B", where={"x": 2})
    line = OrderingLine(Comparison(a, b), "RR", "3DLoMatch", "", 5000, ref_runs=["r1"], row_runs=["r2"])
    line.interval = Interval(4.0, 1.0, 7.0, 0.95, 40, 2, 2000, 0)
    assert line_verdict(+1, line) == HOLDS and line_verdict(-1, line) == REVERSED
    line.interval = Interval(0.5, -1.0, 2.0, 0.95, 40, 2, 2000, 0)
    assert line_verdict(+1, line) == NOT_RESOLVED
    line.interval = None  # runs on both sides, but no per-pair outcomes
    assert line_verdict(+1, line) == NOT_RESOLVED
    line.row_runs = []
    assert line_verdict(+1, line) == NOT_RUN


def test_the_papers_difference_is_placed_against_our_interval():
    """*within*: our interval cannot tell the paper's effect from ours; *above* / *below*: an effect of the paper's
    size is excluded here. A line that is not resolved reads differently in the two cases."""
    from pcrcg.report.orderings import OrderingLine
    from pcrcg.report.spec import Comparison, Row
    from pcrcg.report.stats import Interval

    a, b = Row("A", where={"x": 1}), Row("B", where={"x": 2})
    line = OrderingLine(Comparison(a, b), "RR", "3DLoMatch", "", 5000, paper_ref=59.8, paper_row=66.3,
                        ref_runs=["r1"], row_runs=["r2"])
    line.interval = Interval(0.2, -3.8, 4.3, 0.95, 500, 8, 2000, 0)  # finding 1 of the record: 0 and +6.5 apart
    assert line_verdict(+1, line) == NOT_RESOLVED and paper_position(line) == "above"
    line.interval = Interval(0.5, -3.4, 7.0, 0.95, 500, 8, 2000, 0)
    assert line_verdict(+1, line) == NOT_RESOLVED and paper_position(line) == "within"
    line.interval = Interval(27.4, 22.9, 31.8, 0.95, 500, 8, 2000, 0)  # far larger than the paper's
    assert line_verdict(+1, line) == HOLDS and paper_position(line) == "below"
    line.interval = None
    assert paper_position(line) == DASH
    line.interval, line.paper_row = Interval(0.5, -1.0, 2.0, 0.95, 40, 2, 2000, 0), None  # no paper number
    assert paper_position(line) == DASH


@pytest.mark.parametrize("identity, n_runs, codes", [
    ("config_and_code", 1, "code versions behind the findings: A (2 runs), B (1 run)."),
    ("config", 2, "code versions behind the findings: A (3 runs), B (1 run)."),
])
def test_the_identity_rule_picks_the_runs_and_the_findings_name_their_code(tmp_path, identity, n_runs, codes):
    """PCR-CG's seed 0 run again by newer code B: under config_and_code only that run counts for PCR-CG."""
    from pcrcg.tracking.tracker import RunTracker
    from pcrcg.tracking.store import ensure_store

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    ensure_store(uri)
    rng = np.random.default_rng(9)
    tr = RunTracker(uri, "main_results")
    for seed in (0, 1):
        weak = _base(rng, SCENES, 0.3)
        _run(tr, tmp_path, f"Predator seed={seed}", {"seed": seed}, {"label": "Predator", "code_version": "A"}, weak)
        _run(tr, tmp_path, f"PCR-CG seed={seed}", {"seed": seed, "encoder2d.name": "pri3d"},
             {"label": "PCR-CG", "code_version": "A"}, _more(rng, weak, 0.4))
    _run(tr, tmp_path, "PCR-CG seed=0 again", {"seed": 0, "encoder2d.name": "pri3d"},
         {"label": "PCR-CG", "code_version": "B"}, _base(rng, SCENES, 0.9))
    result = generate_report(_cfg(tmp_path / "out", uri, identity=identity), base_dir=tmp_path)
    [line] = [ln for ln in result.findings.lines if ln.finding.number == 1 and not ln.finding.is_target and ln.ours.at == 5000]
    # under config_and_code PCR-CG has seed 0 only, so Predator is compared on seed 0 too (seed with seed)
    assert len(line.ours.row_runs) == n_runs and len(line.ours.ref_runs) == n_runs
    assert line.ours.n_seeds == (0 if n_runs == 1 else 2)  # a std only where both rows ran two or more seeds
    assert (" ± " in ours_text(line.ours)) == (n_runs == 2)
    md = (tmp_path / "out" / "findings.md").read_text()
    assert codes in md and f"identity={identity}" in md


def _target_store(root: Path, gap: float) -> str:
    """Predator on the generated 3DMatch (seeds 0, 1; every N) and FPFH + RANSAC (seed 0; one estimate per pair),
    Predator registering every pair FPFH does and ``gap`` of each scene's pairs more."""
    from pcrcg.tracking.tracker import RunTracker
    from pcrcg.tracking.store import ensure_store

    uri = f"sqlite:///{root}/mlflow.db"
    ensure_store(uri)
    rng = np.random.default_rng(11)
    scenes = {"kitchen": 60, "office": 40}
    fpfh = _base(rng, scenes, 0.4)
    _run(RunTracker(uri, "sift_dlt"), root / "work", "fpfh seed=0",
         {"seed": 0, "method": "fpfh", "registration.ransac.score": "overlap"}, {"label": "FPFH"},
         fpfh, bench="3DMatch", sizes=(None,))
    main = RunTracker(uri, "main_results")
    for seed in (0, 1):
        _run(main, root / "work", f"Predator seed={seed}", {"seed": seed}, {"label": "Predator"},
             _more(rng, fpfh, gap), bench="3DMatch")
    return uri


@pytest.mark.parametrize("gap, margin, want", [(0.35, 10, "met"), (0.35, 60, "missed"), (0.1, 10, NOT_RESOLVED),
                                               (0.0, 0, "met")])  # the same pairs registered: "at least as often"
def test_a_target_is_met_or_missed_against_its_margin_with_one_estimate_per_pair(tmp_path, gap, margin, want):
    """The profile's target: Predator (every N) against FPFH + RANSAC's one estimate per pair, by a margin.
    Predator's seed 1 is not compared (FPFH ran seed 0 only: seed against seed)."""
    from pcrcg.report.findings import MET, MISSED, target_verdict  # noqa: F401

    uri = _target_store(tmp_path, gap)
    cfg = _cfg(tmp_path / "out", uri)
    cfg["findings"]["targets"][0]["margin"] = margin
    result = generate_report(cfg, base_dir=tmp_path)
    f = result.findings
    target = f.spec.targets[0]
    lines = [ln for ln in f.lines if ln.finding is target]
    assert [ln.ours.at for ln in lines] == [5000, "mean"]
    for ln in lines:
        assert ln.verdict == want and ln.ours.interval is not None and ln.ours.interval.n_pairs == 100
        assert ln.ours.ref_runs and len(ln.ours.row_runs) == 1  # seed 0 against seed 0
        assert ln.real is None and ln.ours.ours_diff == pytest.approx(100 * gap, abs=1.5)
        assert ln.where.endswith("(FPFH + RANSAC: its one estimate per pair)")
    assert f.claim_verdict(target) == want
    md = (tmp_path / "out" / "findings.md").read_text()
    assert "## Targets of the profile" in md and f"| T1. {target.claim} | Predator − FPFH + RANSAC |" in md
    assert f"| ≥ +{margin:.1f} | +" in md
    df = pd.read_csv(tmp_path / "out" / "findings.csv", dtype={"finding": str})
    assert list(df.loc[df["finding"] == "T1", "margin"]) == [margin, margin]
    assert df.loc[df["finding"] == "T1", "real"].isna().all()  # no real-scene column for a target
    tex = (tmp_path / "out" / "findings.tex").read_text()
    assert r"Target $\Delta$" in tex and rf"$\geq$ +{margin:.1f}" in tex and "≥" not in tex


def test_bad_targets_name_the_setting():
    raw = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "report.yaml").findings, resolve=True)
    for change, setting in ((lambda t: t.update(margin=-1), r"targets\[0\]\.margin"),
                            (lambda t: t["rows"][1].update(n_points=None), r"targets\[0\]\.compare"),
                            (lambda t: t["rows"][0].update(n_points=5000), r"targets\[0\]\.rows\[0\]\.n_points"),
                            (lambda t: t["rows"][0].pop("where"), r"targets\[0\]\.rows\[0\]\.where")):
        bad = OmegaConf.to_container(OmegaConf.create(raw))
        change(bad["targets"][0])
        with pytest.raises(ConfigError, match=setting):
            parse_findings(bad)
    assert parse_findings(raw).targets[0].rows[0].paper_table == ""  # a target's row needs no paper entry


def test_the_findings_list_the_seeds_behind_each_job_and_the_command_for_the_missing(report):
    f = report["result"].findings
    by_job = {(r.experiment, r.job): r for r in f.row_seeds}
    assert len(by_job) == len(f.spec.jobs())  # every job once, however many rows it is
    pcrcg = by_job[("main_results", "features=deep")]
    assert pcrcg.names == ["PCR-CG", "deep/explicit", "Pri3D", "11x11"] and pcrcg.seeds == {"0", "1", "2"}
    assert pcrcg.missing(f.spec.seeds) == []
    views = by_job[("views", "views=1")]
    assert views.seeds == {"0"} and views.missing(f.spec.seeds) == [1, 2]
    assert by_job[("sift_dlt", "method=fpfh")].missing(f.spec.seeds) == [0, 1, 2]
    missing = {(r.experiment, r.job): m for r, m in f.missing_runs()}
    assert ("main_results", "features=deep") not in missing and missing[("views", "views=1")] == [1, 2]
    assert missing[("geotransformer", "features=deep")] == [0, 1, 2]
    md = (report["out"] / "findings.md").read_text()
    assert "### Seeds behind the rows" in md
    assert ("| 1 view | `views` views=1 | 0 | 1, 2 | `python -m pcrcg.run +experiment=views views=1 profile=cpu "
            "seed=1,2 -m` |") in md
    assert "| PCR-CG, deep/explicit, Pri3D, 11x11 | `main_results` features=deep | 0, 1, 2 | — | — |" in md


def test_the_findings_say_how_each_rows_model_trained_and_join_a_resumed_trainings_curves(tmp_path):
    """Predator's recall passes the threshold at step 299 in a training stopped after step 449 and resumed (a
    second run of the same config and code, which logs 449 again and 599); PCR-CG's never does."""
    import time

    from pcrcg.report.findings import TrainingRow
    from pcrcg.tracking.store import ensure_store
    from pcrcg.tracking.tracker import RunTracker

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    ensure_store(uri)
    main, work = RunTracker(uri, "main_results"), tmp_path / "work"
    rng = np.random.default_rng(3)
    weak = _base(rng, SCENES, 0.3)
    params = {"seed": 0, "encoder2d.name": "pri3d", "model.loss.matchability_after_recall": 0.3}
    tags = {"experiment": "main_results", "code_version": "v1", "profile": "cpu", "label": "Predator",
            "config_hash": "Predator seed=0"}
    stopped = main.start("Predator seed=0", tags)
    main.log_history(stopped, {"val/recall": [(149, 0.2), (299, 0.31), (449, 0.28)],
                               "val/matchability_gate": [(149, 0), (299, 1), (449, 0)]})
    main.kill(stopped, "stopped")
    other = main.start("Predator seed=0", {**tags, "code_version": "v0"})  # another code's run: not a part
    main.log_history(other, {"val/matchability_gate": [(149, 1), (749, 1)]})
    main.kill(other, "stopped")
    time.sleep(0.01)  # start times in ms: the resumed run starts later
    runs = {}
    for label, ok, recall, gate in (("Predator", weak, [(449, 0.33), (599, 0.36)], [(449, 1), (599, 1)]),
                                    ("PCR-CG", _more(rng, weak, 0.1), [(149, 0.1), (299, 0.2)], [(149, 0), (299, 0)])):
        rid = runs[label] = _run(main, work, f"{label} seed=0", params, {"label": label}, ok)
        main.log_history(rid, {"val/recall": recall, "val/matchability_gate": gate,
                               "val/overlap_recall": [(recall[-1][0], 0.6)]})
        if label == "PCR-CG":
            main.log_metrics(rid, {"color_coverage": 0.127})
    out = tmp_path / "reports"
    result = generate_report(_cfg(out, uri), base_dir=tmp_path, command="python -m pcrcg.report")
    by_label = {t.names[0]: t for t in result.findings.training}
    assert set(by_label) == {"Predator", "PCR-CG"}
    pred, pcr = by_label["Predator"], by_label["PCR-CG"]
    assert pred.run_id == runs["Predator"] and pred.seed == "0" and pred.threshold == 0.3
    # 149 and 299 from the stopped part, 449 from the resumed one (it went on from there), 599: 3 of 4 on, from 299
    assert (pred.gate_on, pred.gate_total, pred.first_on) == (3, 4, 299)
    assert pred.recall_last == pytest.approx(0.36) and pred.recall_best == pytest.approx(0.36)
    assert (pcr.gate_on, pcr.gate_total, pcr.first_on) == (0, 2, None) and pcr.coverage == pytest.approx(0.127)
    md = (out / "findings.md").read_text()
    assert "### How the rows' models trained" in md
    assert "| Predator | `main_results` features=none | 0 | 36.0% (36.0%) | on from step 299 (3 of 4 validations) | 60.0% | — |" in md
    assert ("| PCR-CG, deep/explicit, Pri3D, 11x11 | `main_results` features=deep | 0 | 20.0% (20.0%) | never on "
            "(0 of 2 validations) | 60.0% | 12.7% |") in md
    assert pred.curve == [(149, 0.2), (299, 0.31), (449, 0.33), (599, 0.36)] and pred.on_steps == [299, 449, 599]
    assert (out / "findings_training.png").stat().st_size > 10_000 and "](findings_training.png)" in md
    table = pd.read_csv(out / "findings_training.csv")
    assert list(table["rows"]) == ["Predator", "PCR-CG; deep/explicit; Pri3D; 11x11"] and list(table["gate_on"]) == [3, 0]
    assert TrainingRow([], "e", "j", "0", "r", threshold=0.0).gate_text() == "on from the first step"
    assert TrainingRow([], "e", "j", "0", "r").gate_text() == DASH  # no curve logged
    assert TrainingRow([], "e", "j", "0", "r", threshold=0.0, matchability=False).gate_text().startswith("none")


def test_the_forest_plot_keeps_our_scale_and_draws_a_far_paper_difference_at_the_edge(tmp_path):
    """ICP's paper difference (+67) beside ours (a few points) would squeeze every line: the axis follows ours
    (and paper differences within twice ours), and the far one is drawn at the edge."""
    from types import SimpleNamespace as NS

    from pcrcg.plots.findings import _limit, plot_findings
    from pcrcg.report.stats import Interval

    def line(n, diff, lo, hi, paper, seeds):
        ours = NS(ours_diff=diff, by_seed=seeds, interval=Interval(diff, lo, hi, 0.95, 100, 2, 2000, 0),
                  paper_diff=paper, at=5000, ref_runs=["a"], row_runs=["b"])
        return NS(finding=NS(label=str(n), number=n, is_target=False, benchmark="3DLoMatch"), comparison=f"B{n} − A{n}",
                  ours=ours, real=None, verdict=HOLDS, real_verdict=None)

    lines = [line(1, 2.0, 0.5, 3.5, 6.5, {"0": 1.0, "1": 3.0}), line(8, 4.8, 3.4, 6.2, 67.1, {"0": 4.7, "1": 4.9})]
    lim = _limit(lines, real=False)
    assert 6.5 < lim < 8.0  # ours reach 6.2 and the paper's +6.5 is within twice that: shown; +67 is not
    filled = NS(lines=lines, spec=NS(real=None))
    assert plot_findings(filled, tmp_path / "f.png").stat().st_size > 5_000
    assert plot_findings(NS(lines=[], spec=NS(real=None)), tmp_path / "none.png") is None


def test_runs_ranked_by_inlier_correspondences_make_their_own_findings_and_never_mix_into_the_paper_protocol(tmp_path):
    """main_results holds both rankings of the same jobs: by overlap (the paper's protocol, PCR-CG ahead) and by
    inlier correspondences (Predator ahead). The default report counts only the first; the report made with
    the overrides of `--report-overrides --registration inlier_ranking` only the second, says so, and prints
    the commands of the missing seeds with the group."""
    from pcrcg.report.findings import registration_overrides
    from pcrcg.tracking.store import ensure_store
    from pcrcg.tracking.tracker import RunTracker

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    ensure_store(uri)
    rng, main, work = np.random.default_rng(11), RunTracker(uri, "main_results"), tmp_path / "work"
    for seed in (0, 1):
        weak = _base(rng, SCENES, 0.3)
        strong = _more(rng, weak, 0.4)
        for score, ahead in (("overlap", "PCR-CG"), ("correspondences", "Predator")):
            for label in ("Predator", "PCR-CG"):
                _run(main, work, f"{label} {score} seed={seed}",
                     {"seed": seed, "encoder2d.name": "pri3d", "registration.ransac.score": score},
                     {"label": label}, strong if label == ahead else weak)
    [override] = registration_overrides("inlier_ranking")
    key, value = override.removeprefix("++where.").split("=")
    assert (key, value) == ("registration.ransac.score", "'correspondences'")
    paper = generate_report(_cfg(tmp_path / "paper", uri), base_dir=tmp_path)
    inlier = generate_report(_cfg(tmp_path / "inlier", uri, where={"registration": {"ransac": {"score": "correspondences"}}}),
                             base_dir=tmp_path)
    for result, verdict in ((paper, HOLDS), (inlier, REVERSED)):
        f = result.findings
        assert f.claim_verdict(f.spec.claims[0]) == verdict
        lines = [ln for ln in f.lines if ln.finding.number == 1 and not ln.finding.is_target]
        assert all(len(ln.ours.ref_runs) == 2 and len(ln.ours.row_runs) == 2 for ln in lines)
    assert paper.findings.spec.registration is None and inlier.findings.spec.registration == "inlier_ranking"
    md = (tmp_path / "inlier" / "findings.md").read_text()
    assert "counts the runs registered with `registration=inlier_ranking`, not the paper's protocol" in md
    assert ("`python -m pcrcg.run +experiment=main_results features=none registration=inlier_ranking profile=cpu "
            "seed=2 -m`") in md
    assert ("`python -m pcrcg.run +experiment=main_results features=none profile=cpu seed=2 -m`"
            in (tmp_path / "paper" / "findings.md").read_text())
    assert "`registration.ransac.score=correspondences`" in (tmp_path / "inlier" / "README.md").read_text()
