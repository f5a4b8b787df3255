"""The report: paper layout against paper_tables.csv, seeds as mean ± std, reasons, traceability."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from pcrcg.config import CONF_DIR
from pcrcg.report import generate_report
from pcrcg.report.spec import parse_specs
from pcrcg.report.tables import PAPER_CSV, _paper_value, load_paper, paper_values

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
N = (5000, 2500, 1000, 500, 250)


def _report_cfg(out_dir: Path, uri: str, **extra) -> dict:
    raw = OmegaConf.load(CONF_DIR / "report.yaml")
    for key in ("hydra", "defaults"):
        raw.pop(key, None)
    cfg = OmegaConf.to_container(raw, resolve=True)
    cfg.update(out_dir=str(out_dir), tracking_uri=uri, **extra)
    return cfg


def _rr(ws: int, seed: int, n: int) -> float:
    return 40.0 + ws + seed + (5000 - n) / 1000.0


def _log(tr, name, params, tags, metrics, status="FINISHED", error=None):
    """One fake run; ranked as the paper's protocol ranks (the report's default ``where``) unless ``params`` say."""
    rid = tr.start(name, {"experiment": tr.experiment_name, "git_sha": "a" * 40, **tags})
    tr.log_params(rid, {"registration.ransac.score": "overlap", **params})
    tr.log_metrics(rid, metrics)
    if status == "FINISHED":
        tr.finish(rid)
    elif status == "FAILED":
        tr.fail(rid, error or RuntimeError("boom"))
    return rid


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Runs of three experiments logged directly (no pipeline): known numbers everywhere."""
    from pcrcg.tracking.tracker import RunTracker
    from pcrcg.tracking.store import ensure_store

    root = tmp_path_factory.mktemp("report")
    uri = f"sqlite:///{root}/mlflow.db"
    ensure_store(uri)
    ids = {}
    tr = RunTracker(uri, "window_size")
    # an older run of 11x11 seed 0 whose config changed since: the newer run of that seed counts
    ids["old"] = _log(tr, "window_size=11", {"window_size": 11, "seed": 0, "encoder2d.name": "pri3d"},
                      {"config_hash": "old110", "profile": "cpu", "label": "PCR-CG"},
                      {f"3DLoMatch/rr_{n}": 0.0 for n in N})
    for ws in (3, 7, 11):
        for seed in (0, 1):
            metrics = {f"3DLoMatch/rr_{n}": _rr(ws, seed, n) for n in N}
            metrics["color_coverage"] = 0.5 + 0.1 * seed
            ids[(ws, seed)] = _log(tr, f"window_size={ws}", {"window_size": ws, "seed": seed, "encoder2d.name": "pri3d",
                                                            "protocol.3DLoMatch.n_pairs": 1781,
                                                            "eval.ransac_iterations": 50000},
                                   {"config_hash": f"h{ws}{seed}", "profile": "cpu", "label": "PCR-CG"}, metrics)
    _log(tr, "window_size=17", {"window_size": 17, "seed": 0, "encoder2d.name": "pri3d"}, {"config_hash": "h170", "profile": "cpu"}, {},
         status="FAILED", error=MemoryError("out of memory at 17x17"))
    # a tiny-profile run that must not leak into the cpu table
    _log(tr, "window_size=3", {"window_size": 3, "seed": 5, "encoder2d.name": "pri3d"}, {"config_hash": "t3", "profile": "tiny"},
         {f"3DLoMatch/rr_{n}": 1.0 for n in N})
    tr = RunTracker(uri, "main_results")
    for label, base in (("Predator", 60.0), ("PCR-CG", 66.0)):
        metrics = {}
        for b, off in (("3DMatch", 25.0), ("3DLoMatch", 0.0)):
            for n in N:
                metrics[f"{b}/rr_{n}"] = base + off
                metrics[f"{b}/fmr_{n}"] = base + off + 5
            metrics[f"{b}/rre"], metrics[f"{b}/rte"] = 2.5, 0.08
        _log(tr, f"features={'none' if label == 'Predator' else 'deep'}", {"seed": 0, "icp_init": "identity", "encoder2d.name": "pri3d"},
             {"config_hash": f"m{label}", "profile": "cpu", "label": label}, metrics)
    tr = RunTracker(uri, "icp_init")
    for method in ("icp", "color_icp"):
        for init, v in (("identity", 3.0), ("learned", 70.0)):
            _log(tr, f"method={method} icp_init={init}", {"method": method, "icp_init": init, "seed": 0},
                 {"config_hash": f"{method}{init}", "profile": "cpu"},
                 {"3DMatch/rr": v + 20, "3DLoMatch/rr": v})
    # a run that never ended (crashed worker)
    views = RunTracker(uri, "views")
    rid = views.start("views=1", {"config_hash": "v1", "profile": "cpu", "experiment": "views"})
    views.log_params(rid, {"views": 1, "projection.name": "implicit", "encoder2d.name": "pri3d", "seed": 0,
                           "registration.ransac.score": "overlap"})
    out = root / "reports"
    result = generate_report(_report_cfg(out, uri, profile="cpu"), base_dir=root, command="python -m pcrcg.report")
    return {"uri": uri, "root": root, "out": out, "ids": ids, "result": result, "running": rid}


def test_every_table_and_file_is_written(store):
    out = store["out"]
    names = list(parse_specs(OmegaConf.to_container(OmegaConf.load(CONF_DIR / "report.yaml").specs,
                                                    resolve=True)))
    assert names == ["main_results", "rre_rte", "window_size", "views", "views_explicit", "backbone_2d", "projection", "icp_init",
                     "sift_dlt", "ransac_budget", "explicit_input", "geotransformer", "cofinet", "default", "ablations_3dmatch"]
    for name in names:
        for suffix in ("md", "tex", "csv"):
            assert (out / f"{name}.{suffix}").stat().st_size > 100, name
    assert (out / "window_size_recall.png").is_file() and (out / "window_size_coverage.png").is_file()
    index = (out / "README.md").read_text()
    assert "python -m pcrcg.report" in index and "mlflow.db" in index
    assert "- 3DLoMatch: n_pairs 1781" in index and "- seeds 0, 1" in index
    assert "`eval.ransac_iterations`: 50000" in index
    # per table: the experiments its rows read and the runs behind its cells (not every finished run of them)
    line = next(x for x in index.splitlines() if x.startswith("| window_size |"))
    df = pd.read_csv(out / "window_size.csv", dtype={"variant": str})
    behind = {r for ids in df["run_ids"].dropna() for r in str(ids).split(";")}
    assert line.startswith(f"| window_size | window_size, main_results | cpu | {len(behind)} |"), (line, behind)


def test_layout_follows_paper_tables_csv(store):
    """Every paper number of every rendered table sits in exactly one cell, in the paper's place."""
    paper = load_paper()
    got = pd.concat([pd.read_csv(store["out"] / f"{t}.csv", dtype={"variant": str}) for t in
                     ("main_results", "rre_rte", "window_size", "views", "backbone_2d", "projection", "icp_init",
                      "sift_dlt", "geotransformer", "cofinet")])
    got["variant"] = got["variant"].fillna("")
    for table in got["table"].unique():
        want = paper[paper["table"] == table]
        assert len(want) > 0, table
        cells = got[(got["table"] == table) & got["paper"].notna()]
        assert len(cells) == len(want), table
        for _, p in want.iterrows():
            n = "" if math.isnan(p["n_points"]) else int(p["n_points"])
            hit = cells[(cells["method"] == p["method"]) & (cells["variant"] == p["variant"])
                        & (cells["benchmark"] == p["benchmark"]) & (cells["metric"] == p["metric"])
                        & (cells["n_points"].fillna("").astype(str).str.replace(".0", "", regex=False) == str(n))]
            assert len(hit) == 1 and hit.iloc[0]["paper"] == pytest.approx(p["value"]), (table, dict(p))


def test_paper_values_index_each_number_by_its_cell_and_keep_the_first_of_a_key():
    """The paper's numbers by (table, method, variant, benchmark, metric, n_points): a number of the paper per
    cell (an integer n_points finds the CSV's float, a blank n_points is None), the first row where a key repeats,
    and a row with a missing text field selects nothing."""
    from pcrcg.report.spec import Column, Row

    paper = pd.DataFrame({"table": ["t", "t", "t", "t", "t"], "method": ["A", "A", "A", None, "A"],
                          "variant": ["", "", "", "", "x"], "benchmark": ["3DMatch"] * 5,
                          "metric": ["rr", "rr", "rr", "rr", "rre"],
                          "n_points": [5000.0, 5000.0, np.nan, 250.0, np.nan], "value": [1.0, 2.0, 3.0, 4.0, 5.0]})
    values = paper_values(paper)
    assert values == {("t", "A", "", "3DMatch", "rr", 5000.0): 1.0, ("t", "A", "", "3DMatch", "rr", None): 3.0,
                      ("t", "A", "x", "3DMatch", "rre", None): 5.0}
    row = Row(method="A")
    assert _paper_value(values, "t", row, Column(benchmark="3DMatch", metric="rr", n_points=5000)) == 1.0
    assert _paper_value(values, "t", row, Column(benchmark="3DMatch", metric="rr", n_points=None)) == 3.0
    assert _paper_value(values, "t", row, Column(benchmark="3DMatch", metric="rr", n_points=250)) is None
    assert _paper_value(values, "t", row, Column(benchmark="3DMatch", metric="rre", variant="x")) == 5.0
    # the shipped copy: one number per key, none lost
    assert len(paper_values(load_paper())) == len(load_paper())


def test_markdown_columns_in_paper_order(store):
    md = (store["out"] / "main_results.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("| | 3DMatch"))
    cols = [c.strip() for c in header.strip("|").split("|")][1:]
    assert cols == [f"{b} {n}" for b in ("3DMatch", "3DLoMatch") for n in N]
    assert md.index("**Feature Matching Recall (%)**") < md.index("**Registration Recall (%)**")
    # published baselines: the paper's numbers with the reason they are not re-run
    assert "| 3DSN (paper) [1] | 95.0 | 94.3 | 92.9 | 90.1 | 82.9 | 63.6 |" in md
    assert "1. a published method the paper compares with; not re-run here" in md
    # ours beside the paper's, and the difference
    assert "| PCR-CG (paper) | 89.4 | 90.7 | 90.0 | 88.7 | 86.8 | 66.3 | 67.2 | 69.0 | 68.5 | 65.0 |" in md
    assert "| PCR-CG (ours) | 91.0 | 91.0 | 91.0 | 91.0 | 91.0 | 66.0 |" in md
    assert "| PCR-CG (Δ ours − paper) | +1.6 | +0.3 | +1.0 | +2.3 | +4.2 | -0.3 |" in md


def test_seeds_are_aggregated_as_mean_and_std(store):
    df = pd.read_csv(store["out"] / "window_size.csv", dtype={"variant": str})
    cell = df[(df["variant"] == "7x7") & (df["n_points"] == 1000)].iloc[0]
    vals = [_rr(7, 0, 1000), _rr(7, 1, 1000)]
    assert cell["n_runs"] == 2
    assert cell["ours_mean"] == pytest.approx(np.mean(vals), abs=1e-4)
    assert cell["ours_std"] == pytest.approx(np.std(vals, ddof=1), abs=1e-4)
    assert cell["diff"] == pytest.approx(np.mean(vals) - 67.1, abs=1e-4)
    assert set(cell["run_ids"].split(";")) == {store["ids"][(7, 0)], store["ids"][(7, 1)]}
    assert cell["config_hashes"] == "h70;h71" and cell["profiles"] == "cpu;cpu" and cell["seeds"] == "0;1"
    assert cell["git_shas"] == ";".join(["a" * 40] * 2)
    md = (store["out"] / "window_size.md").read_text()
    assert f"{np.mean(vals):.1f} ± {np.std(vals, ddof=1):.1f}" in md
    assert f"run {store['ids'][(7, 0)][:8]} · hash h70 · git aaaaaaa · profile cpu · seed 0" in md
    assert "Protocol of these runs: 3DLoMatch: n_pairs 1781; RANSAC iterations 50000; seeds 0, 1" in md


def test_newest_run_per_seed_counts(store):
    df = pd.read_csv(store["out"] / "window_size.csv", dtype={"variant": str})
    cell = df[(df["variant"] == "11x11") & (df["n_points"] == 5000)].iloc[0]
    assert cell["n_runs"] == 2 and store["ids"]["old"] not in cell["run_ids"]
    assert cell["ours_mean"] == pytest.approx((_rr(11, 0, 5000) + _rr(11, 1, 5000)) / 2)


def test_profile_filter_keeps_other_profiles_out(store):
    df = pd.read_csv(store["out"] / "window_size.csv", dtype={"variant": str})
    assert set(";".join(df["profiles"].dropna()).split(";")) == {"cpu"}
    assert (df[df["variant"] == "3x3"]["n_runs"] == 2).all()


def test_failed_missing_and_running_cells_are_dashes_with_reasons(store):
    df = pd.read_csv(store["out"] / "window_size.csv", dtype={"variant": str})
    row17 = df[df["variant"] == "17x17"]
    assert (row17["status"] == "missing").all()
    assert row17["reason"].str.startswith("failed: out of memory at 17x17 (run ").all()
    md = (store["out"] / "window_size.md").read_text()
    assert "| PCR-CG 17x17 (ours) | — [1] | — [1] | — [1] | — [1] | — [1] |" in md
    assert "1. failed: out of memory at 17x17" in md
    views = pd.read_csv(store["out"] / "views.csv", dtype={"variant": str})
    one = views[views["variant"] == "1"].iloc[0]
    assert one["reason"] == f"still running or crashed (run {store['running'][:8]})"
    two = views[views["variant"] == "2"].iloc[0]
    assert two["reason"] == ("no run of experiment 'views' with views=2, projection.name=implicit, encoder2d.name=pri3d, "
                             "registration.ransac.score=overlap at profile cpu; nor of experiment 'projection' (features.name=deep)")
    tex = (store["out"] / "window_size.tex").read_text()
    assert r"PCR-CG 17x17 (ours) & -- [1] & -- [1] & -- [1] & -- [1] & -- [1] \\" in tex
    assert "% [1] failed: out of memory" in tex


def test_cells_from_columns_and_other_experiments(store):
    """icp_init: the column picks the initial pose, the PCR-CG row comes from main_results."""
    df = pd.read_csv(store["out"] / "icp_init.csv", dtype={"variant": str})
    get = lambda m, v, b: df[(df["method"] == m) & (df["variant"] == v) & (df["benchmark"] == b)].iloc[0]  # noqa: E731
    assert get("ICP", "original", "3DLoMatch")["ours_mean"] == 3.0
    assert get("ICP", "improved", "3DMatch")["ours_mean"] == 90.0
    assert get("ColorICP", "improved", "3DLoMatch")["paper"] == 68.8
    pcr = get("PCR-CG", "original", "3DLoMatch")
    assert pcr["ours_mean"] == 66.0 and pcr["metric_key"] == "3DLoMatch/rr_5000"
    rre = pd.read_csv(store["out"] / "rre_rte.csv")
    cell = rre[(rre["method"] == "PCR-CG") & (rre["benchmark"] == "3DLoMatch") & (rre["metric"] == "RTE_m")].iloc[0]
    assert cell["ours_mean"] == 0.08 and cell["paper"] == 0.087
    md = (store["out"] / "rre_rte.md").read_text()
    assert "| PCR-CG (ours) | 2.500 | 0.080 | 2.500 | 0.080 |" in md


def test_latex_table_structure(store):
    tex = (store["out"] / "main_results.tex").read_text()
    assert r"\begin{tabular}{l|cccccccccc}" in tex
    assert r"\multicolumn{5}{c}{\textbf{3DMatch}} & \multicolumn{5}{c}{\textbf{3DLoMatch}}" in tex
    assert r"\# Sampled Points & 5000 & 2500 & 1000 & 500 & 250 & 5000" in tex
    assert r"PCR-CG ($\Delta$ ours $-$ paper) & +1.6" in tex
    first = tex.split(r"\end{table}")[0]  # the paper's table; the orderings tested follow in their own
    body = [ln for ln in first.splitlines() if ln.endswith(r"\\") and "&" in ln]
    assert all(ln.count("&") == 10 for ln in body if not ln.startswith("&") and "multicolumn" not in ln)


def test_report_cli(store, monkeypatch, capsys):
    from pcrcg.report import __main__ as report_main

    out = store["root"] / "cli"
    monkeypatch.chdir(store["root"])
    monkeypatch.setenv("MLFLOW_TRACKING_URI", store["uri"])
    monkeypatch.setattr("sys.argv", ["pcrcg.report", "--config-path", str(CONF_DIR), f"out_dir={out}", "profile=cpu", "tables=[window_size]"])
    report_main.main()
    text = capsys.readouterr().out
    assert f"start here: {out / 'README.md'}" in text
    assert sorted(p.name for p in out.iterdir()) == ["README.md", "findings.csv", "findings.md", "findings.png",
                                                     "findings.tex", "window_size.csv", "window_size.md", "window_size.tex",
                                                     "window_size_coverage.png", "window_size_orderings.csv",
                                                     "window_size_recall.png"]


def test_report_cli_refuses_a_store_that_is_not_there(tmp_path, monkeypatch, capsys):
    """A missing store is one line and exit 2 before anything is written: tables of no runs would replace the
    committed ones, and MLflow would create the database file (a run's own report keeps writing them)."""
    from pcrcg.report import __main__ as report_main

    out, db = tmp_path / "out", tmp_path / "none" / "mlflow.db"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["pcrcg.report", "--config-path", str(CONF_DIR), f"out_dir={out}",
                                     f"tracking_uri=sqlite:///{db}"])
    with pytest.raises(SystemExit) as info:
        report_main.main()
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"pcrcg.report: error: {db}: no MLflow store there (tracking_uri=... or MLFLOW_TRACKING_URI; "
                   "python -m pcrcg.run makes it)"]
    assert not out.exists() and not db.exists() and not db.parent.exists()


def test_shipped_paper_numbers_match_the_shared_copy():
    if not (SHARED / "paper" / "paper_tables.csv").is_file():
        pytest.skip("../shared is not here")
    assert PAPER_CSV.read_bytes() == (SHARED / "paper" / "paper_tables.csv").read_bytes()


@pytest.fixture(scope="module")
def code_store(tmp_path_factory):
    """window_size 3x3, seeds 0 and 1 run by code A, then seed 0 again by code B (an edit since)."""
    from mlflow.tracking import MlflowClient

    from pcrcg.tracking.store import ensure_experiment, ensure_store

    root = tmp_path_factory.mktemp("codes")
    uri = f"sqlite:///{root}/mlflow.db"
    ensure_store(uri)
    client = MlflowClient(uri)
    exp = ensure_experiment(client, "window_size", uri)
    machine = {"A": ("AMD EPYC 7B13", "AVX2"), "B": ("Intel(R) Xeon(R) Processor", "AVX512")}
    for t, (code, seed, rr) in enumerate((("A", 0, 40.0), ("A", 1, 50.0), ("B", 0, 70.0))):
        run = client.create_run(exp, start_time=1_000_000 + 1000 * t, run_name="window_size=3",
                                tags={"experiment": "window_size", "config_hash": f"h{seed}", "profile": "cpu",
                                      "git_sha": "c" * 40, "code_version": code, "pcrcg.cpu": machine[code][0],
                                      "pcrcg.cpu_capability": machine[code][1]})
        for key, value in (("window_size", "3"), ("seed", str(seed)), ("encoder2d.name", "pri3d"),
                           ("registration.ransac.score", "overlap")):
            client.log_param(run.info.run_id, key, value)
        client.log_metric(run.info.run_id, "3DLoMatch/rr_5000", rr)
        client.set_terminated(run.info.run_id, "FINISHED")
    return root, uri


@pytest.mark.parametrize("identity, mean, n_runs, rule", [
    ("config_and_code", 70.0, 1, "Runs counted: same config and code (identity=config_and_code)"),
    ("config", 60.0, 2, "Runs counted: same config (identity=config)"),
])
def test_the_identity_setting_picks_the_runs_of_a_cell_and_the_table_says_which(code_store, identity, mean, n_runs,
                                                                                rule):
    root, uri = code_store
    out = root / identity
    generate_report(_report_cfg(out, uri, tables=["window_size"], profile="cpu", identity=identity), base_dir=root)
    df = pd.read_csv(out / "window_size.csv", dtype={"variant": str})
    cell = df[(df["variant"] == "3x3") & (df["n_points"] == 5000)].iloc[0]
    assert cell["ours_mean"] == pytest.approx(mean) and cell["n_runs"] == n_runs
    md = (out / "window_size.md").read_text()
    codes = "B (1 run)" if identity == "config_and_code" else "A (1 run), B (1 run)"
    assert f"{rule}" in md and f"code versions behind the cells: {codes}." in md
    intel, amd = "Intel(R) Xeon(R) Processor (AVX512) (1 run)", "AMD EPYC 7B13 (AVX2) (1 run)"
    machines = intel if identity == "config_and_code" else sorted([intel, amd])
    assert all(m in md for m in ([machines] if isinstance(machines, str) else machines))
    assert "Machines behind them: " in md and (identity == "config" or "AMD" not in md)
    assert f"`identity={identity}`" in (out / "README.md").read_text()


def test_run_machine_reads_the_machine_tags_and_says_unrecorded_before_them():
    from pcrcg.report.tables import machines_text, run_machine
    from pcrcg.tracking.tracker import machine_tags

    df = pd.DataFrame({"tags.pcrcg.cpu": ["Intel(R) Xeon(R) Processor", "AMD EPYC 7B13", None],
                       "tags.pcrcg.cpu_capability": ["AVX512", None, None],
                       "tags.pcrcg.cuda": [None, "NVIDIA H100 80GB HBM3", None]})
    assert list(run_machine(df)) == ["Intel(R) Xeon(R) Processor (AVX512)", "AMD EPYC 7B13 + NVIDIA H100 80GB HBM3",
                                     "unrecorded"]
    assert list(run_machine(pd.DataFrame({"x": [1]}))) == ["unrecorded"]
    assert machines_text({}) == "" and machines_text({"m": 2, "n": 1}) == " Machines behind them: m (2 runs), n (1 run)."
    tags = machine_tags()  # this machine's
    assert tags["pcrcg.cpu"] and tags["pcrcg.cpu_capability"] and run_machine(
        pd.DataFrame({f"tags.{k}": [v] for k, v in tags.items()}))[0].startswith(tags["pcrcg.cpu"])


def test_a_bad_identity_is_one_line_naming_the_setting(code_store):
    from pcrcg.errors import ConfigError

    root, uri = code_store
    with pytest.raises(ConfigError, match="identity='code'"):
        generate_report(_report_cfg(root / "bad", uri, tables=["window_size"], identity="code"), base_dir=root)


def test_runs_recorded_before_the_code_version_tag_count_by_their_commit():
    from pcrcg.report.tables import run_code

    runs = pd.DataFrame({"tags.code_version": ["v1", None, None, None],
                         "tags.git_sha": ["a" * 40, "b" * 40, "b" * 40, None],
                         "tags.git_dirty": ["false", "false", "true", None]})
    assert run_code(runs).tolist() == ["v1", "git bbbbbbb", "git bbbbbbb+dirty", "unrecorded"]
