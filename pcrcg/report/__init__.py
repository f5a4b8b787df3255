"""Generated paper tables: ``python -m pcrcg.report [out_dir=reports/] [profile=cpu] [tables=[window_size]]``.

Reads the runs of the MLflow store (same resolution as ``pcrcg.run``), fills every table
spec of ``conf/report.yaml`` and writes ``<out_dir>/<table>.{md,tex,csv}``, the figures
``<table>_recall.png`` / ``<table>_coverage.png`` and ``<out_dir>/README.md`` (all tables,
protocol per benchmark, seeds, how well our trends follow the paper's).

Tables that compare rows (``compare``) also test the paper's orderings with a paired bootstrap
over the test pairs (``stats`` in conf/report.yaml; :mod:`pcrcg.report.orderings`), under the
table and in ``<table>_orderings.csv``.

Every report also writes the paper's findings (``findings`` in conf/report.yaml,
:mod:`pcrcg.report.findings`): ``<out_dir>/findings.{md,tex,csv}`` and a section of README.md.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import pandas as pd
from omegaconf import DictConfig, OmegaConf

from pcrcg.errors import ConfigError
from pcrcg.plots.recall import plot_coverage, plot_table_recall
from pcrcg.tracking.git import DEFAULT_IDENTITY, IDENTITIES, same_code
from pcrcg.report.orderings import StatsSettings, check_orderings
from pcrcg.report.outcomes import OutcomeSource
from pcrcg.report.render import to_latex, to_markdown, write_csv, write_orderings_csv
from pcrcg.report.load import load_runs, newest_profile
from pcrcg.report.spec import TableSpec, parse_specs, report_where
from pcrcg.report.tables import FilledTable, fill_table, load_paper, protocol_summary, trend_agreement

if TYPE_CHECKING:  # imported where used: `python -m pcrcg.report.findings` runs that module as a script
    from pcrcg.report.findings import FilledFindings

__all__ = ["ReportResult", "generate_report", "tables_for_experiment", "write_experiment_tables"]


@dataclass
class ReportResult:
    out_dir: Path
    tracking_uri: str
    files: list[Path] = field(default_factory=list)
    tables: dict[str, FilledTable] = field(default_factory=dict)
    identity: str = DEFAULT_IDENTITY
    findings: FilledFindings | None = None
    where: Mapping[str, Any] = field(default_factory=dict)  # the report-wide filters (conf/report.yaml `where`)

    @property
    def index(self) -> Path:
        return self.out_dir / "README.md"


def _plain(cfg: DictConfig | Mapping[str, Any]) -> dict[str, Any]:
    if isinstance(cfg, DictConfig):
        data = OmegaConf.to_container(cfg, resolve=True)
        assert isinstance(data, dict)
        data.pop("hydra", None)
        return data
    return dict(cfg)


def tables_for_experiment(specs: Mapping[str, TableSpec], experiment: str) -> list[str]:
    """Names of the tables whose main experiment is ``experiment``."""
    return [n for n, s in specs.items() if s.experiment == experiment]


def _select(specs: Mapping[str, TableSpec], tables: Any) -> list[str]:
    if tables in (None, "all"):
        return list(specs)
    names = [tables] if isinstance(tables, str) else list(tables)
    for n in names:
        if n not in specs:
            raise ConfigError("tables", n, "all or a list of " + ", ".join(specs))
    return names


def generate_report(cfg: DictConfig | Mapping[str, Any], base_dir: str | os.PathLike | None = None,
                    command: str | None = None, require_store: bool = False) -> ReportResult:
    """Write the report described by ``cfg`` (the ``conf/report.yaml`` node). See module docstring.
    ``require_store``: a SQLite store that is not there is an error before anything is written (the command
    line's: tables of no runs would replace the committed ones); a run's own report (``pcrcg.run``) writes them."""
    from pcrcg.tracking.store import require_store as check_store
    from pcrcg.tracking.store import resolve_tracking_uri

    c = _plain(cfg)
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    defaults = report_where(c)
    specs = parse_specs(c["specs"], defaults)
    names = _select(specs, c.get("tables", "all"))
    settings = StatsSettings.from_dict(c.get("stats"))  # a bad setting stops the report before it reads or writes
    out_dir = Path(str(c.get("out_dir") or "reports"))
    out_dir = out_dir if out_dir.is_absolute() else base / out_dir
    uri = resolve_tracking_uri(c.get("tracking_uri"), base)
    if require_store:
        check_store(uri, "tracking_uri=... or MLFLOW_TRACKING_URI; python -m pcrcg.run makes it")
    out_dir.mkdir(parents=True, exist_ok=True)
    from pcrcg.report.findings import fill_findings, parse_findings, write_findings

    experiments = sorted({e for n in names for e in specs[n].experiments})
    findings = parse_findings(c.get("findings"), defaults)
    found = findings.experiments if findings is not None else []
    all_runs = load_runs(uri, sorted(set(experiments) | set(found)))
    runs = all_runs[all_runs["experiment"].isin(experiments)] if len(all_runs) else all_runs
    paper = load_paper(c.get("paper_csv"))
    wanted = _profile_name(c.get("profile"))
    profiles = {e: wanted or newest_profile(all_runs, e) for e in sorted(set(experiments) | set(found))}

    identity = c.get("identity", DEFAULT_IDENTITY)
    if identity not in IDENTITIES:
        raise ConfigError("identity", identity, " | ".join(IDENTITIES))

    result = ReportResult(out_dir, uri, identity=identity, where=defaults)
    with OutcomeSource(uri, base, all_runs) as source:
        for name in names:
            table = fill_table(specs[name], runs, paper, profiles, identity)
            table.orderings = check_orderings(table, source, settings)
            result.tables[name] = table
        if findings is not None:
            result.findings = fill_findings(findings, all_runs, paper, profiles, source, settings, identity)
    if result.findings is not None:
        result.files += write_findings(result.findings, out_dir)
    for name, table in result.tables.items():
        for suffix, text in (("md", to_markdown(table)), ("tex", to_latex(table))):
            p = out_dir / f"{name}.{suffix}"
            p.write_text(text)
            result.files.append(p)
        write_csv(table, out_dir / f"{name}.csv")
        result.files.append(out_dir / f"{name}.csv")
        p = write_orderings_csv(table, out_dir / f"{name}_orderings.csv")
        if p is not None:
            result.files.append(p)
        for fn, suffix in ((plot_table_recall, "recall"), (plot_coverage, "coverage")):
            p = fn(table, out_dir / f"{name}_{suffix}.png")
            if p is not None:
                result.files.append(p)
    result.index.write_text(_index(result, runs, experiments, profiles, command))
    result.files.append(result.index)
    return result


def write_experiment_tables(experiment: str, uri: str, profile: str | None, out_dir: str | os.PathLike,
                            base_dir: str | os.PathLike, prefix: str = "[report]") -> list[Path]:
    """Write the tables fed by ``experiment`` (conf/report.yaml) and print where they are.

    Used at the end of ``pcrcg.run``; never raises (the runs are safe in MLflow and the report
    can be redone with the printed command). Returns the Markdown files written.
    """
    from pcrcg.config import CONF_DIR

    report_cfg = OmegaConf.load(CONF_DIR / "report.yaml")
    for key in ("hydra", "defaults"):
        report_cfg.pop(key, None)
    specs = parse_specs(OmegaConf.to_container(report_cfg.specs, resolve=True),  # type: ignore[arg-type]
                        report_where(report_cfg))
    names = tables_for_experiment(specs, experiment)
    if not names:
        print(f"{prefix} experiment {experiment!r} feeds no paper table; the tables come from "
              f"`python -m pcrcg.run +experiment=<table> -m` and `python -m pcrcg.report`")
        return []
    command = f"python -m pcrcg.report tables=[{','.join(names)}]" + (f" profile={profile}" if profile else "")
    cfg = OmegaConf.merge(report_cfg, {"tables": names, "tracking_uri": uri, "profile": profile,
                                       "out_dir": str(out_dir)})
    try:
        result = generate_report(cfg, base_dir=base_dir, command=command)
    except Exception as e:  # noqa: BLE001
        print(f"{prefix} could not write the tables ({type(e).__name__}: {e}); later: {command}")
        return []
    files = [result.out_dir / f"{n}.md" for n in names]
    for name, f in zip(names, files):
        print(f"{prefix} table {name}: {f} (also .tex, .csv; all tables: {result.index})")
    return files


def _profile_name(node: Any) -> str | None:
    """``profile`` of the report config: a profile group node (``{name: ...}``), a name, or None."""
    if isinstance(node, Mapping):
        return node.get("name")
    return str(node) if node else None


def _store_text(uri: str, base: Path) -> str:
    from pcrcg.tracking.store import sqlite_path

    db = sqlite_path(uri)
    if db is not None:
        try:
            return f"sqlite:///{db.relative_to(base)}"
        except ValueError:
            return uri
    return uri


def _protocol(runs: pd.DataFrame) -> list[str]:
    """Protocol facts of the finished runs: per benchmark pairs and RANSAC, settings, seeds, code."""
    if runs.empty:
        return ["No runs yet."]
    done = runs[runs["status"] == "FINISHED"]
    lines = [f"- {line}" for line in protocol_summary(done)]
    for col in sorted(c for c in done.columns if c.startswith("params.eval.")):
        vals = done[col].dropna().astype(str).value_counts()
        if len(vals):
            text = ", ".join(f"{v}" + (f" ({n} runs)" if len(vals) > 1 else "") for v, n in vals.items())
            lines.append(f"- `{col[len('params.'):]}`: {text}")
    if "tags.git_sha" in done.columns:
        shas = done["tags.git_sha"].dropna().astype(str).str[:7].unique()
        lines.append(f"- code (git sha): {', '.join(sorted(shas))}")
    return lines or ["No finished run logged protocol settings."]


def _index(result: ReportResult, runs: pd.DataFrame, experiments: Sequence[str],
           profiles: Mapping[str, str | None], command: str | None) -> str:
    base = result.out_dir.parent
    out = ["# PCR-CG tables: ours beside the paper's", ""]
    out.append(f"Generated by `{command or 'python -m pcrcg.report'}` from the MLflow store "
               f"`{_store_text(result.tracking_uri, base)}`.")
    out.append("Open the runs: `mlflow ui --backend-store-uri <store>`; every cell lists its runs "
               "(run id, config hash, git sha, profile, seed), here and in the CSV files.")
    out.append("Runs counted: " + ("the same config and code (`identity=config_and_code`): a cell's seeds come "
                                   "from one code version, that of its newest run." if same_code(result.identity) else
                                   "the same config (`identity=config`): a cell's seeds may come from different "
                                   "code versions (each table lists them)."))
    if result.where:
        out.append("Every row of ours counts only the runs with "
                   + ", ".join(f"`{k}={v}`" for k, v in result.where.items())
                   + " unless it sets the key itself (the report-wide `where` of conf/report.yaml; "
                     "`registration.ransac.score=overlap`: RANSAC ranked as the paper's protocol ranks).")
    out.append("")
    out.append("Paper trend kept: of the row pairs with both numbers, per column, how many we order as the paper "
               "does (signs only). Paper orderings beyond noise: of the orderings the table tests (`compare`), "
               "how many hold / are reversed beyond the paired bootstrap interval over the test pairs / lie "
               "within noise; untested ones (no per-pair outcomes, or no run of ours) are counted apart.")
    out.append("")
    out.append("| Table | Experiments | Profile | Runs behind the cells | Paper trend kept (row pairs) "
               "| Paper orderings: holds / reversed / within noise (untested) | Files |")
    out.append("|---|---|---|---:|---|---|---|")
    for name, table in result.tables.items():
        exp = table.spec.experiment
        # the table's own experiment first, then those its rows read (rows[].experiment, rows[].same_as)
        exps = ", ".join(table.spec.experiments)
        n_done = len({r.run_id for c in table.cells for r in c.runs})
        t = trend_agreement(table)
        trend = f"{t['agree']}/{t['pairs']}" if t["pairs"] else "n/a"
        o = t["orderings"]
        orderings = f"{o['holds']} / {o['reversed']} / {o['within_noise']}" if o["tested"] or o["untested"] else "n/a"
        extra = ([f"{o['untested']} untested"] if o["untested"] else []) + (
            [f"{o['no_ordering']} without a paper ordering"] if o["no_ordering"] else [])
        if extra:
            orderings += f" ({'; '.join(extra)})"
        files = ", ".join(f"[{s}]({name}.{s})" for s in ("md", "tex", "csv"))
        if table.orderings:
            files += f", [orderings]({name}_orderings.csv)"
        out.append(f"| {name} | {exps} | {profiles.get(exp) or '—'} | {n_done} | {trend} | {orderings} | {files} |")
    out += ["", "## Protocol (from the runs' logged settings)", ""]
    out += _protocol(runs)
    out.append("")
    out += ["### Settings that differ from the paper's text or its official code, per table", "",
            "Where the text and the code (Gardlin/PCR-CG) disagree, the published numbers came from the code.", ""]
    for name, table in result.tables.items():
        out.append(f"- {name}: " + ("; ".join(table.fidelity) if table.fidelity else "none found in its runs "
                                     "(or no runs yet)"))
    out.append("")
    if result.findings is not None:
        from pcrcg.report.findings import FIGURE
        from pcrcg.report.findings import to_markdown as findings_markdown

        figure = FIGURE if (result.out_dir / FIGURE).is_file() else None
        out.append(findings_markdown(result.findings, figure=figure).replace(
            "## The paper's findings, tested", "## The paper's findings, tested ([md](findings.md), "
            "[tex](findings.tex), [csv](findings.csv))", 1))
    for name, table in result.tables.items():
        out.append(to_markdown(table))
        for suffix in ("recall", "coverage"):
            if (result.out_dir / f"{name}_{suffix}.png").is_file():
                out.append(f"![{name} {suffix}]({name}_{suffix}.png)")
                out.append("")
    return "\n".join(out)
