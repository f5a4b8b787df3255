"""Fill a table spec from runs and the paper's numbers: one :class:`Cell` per (row, column).

Seeds are aggregated as mean and sample standard deviation; of several FINISHED runs of a
cell with the same seed (the same config run again, or a config that changed since) the
newest counts. With ``identity=config_and_code`` (the default) a cell counts only the runs of one
code version, that of its newest run; with ``identity=config`` its seeds may come from different code.
A cell without a finished run carries the reason (failed with its error, not run with its
reason, still running, no such run, or the row's own reason). A row with ``same_as`` also counts the
runs of the other experiment that runs its config (``pcrcg.report.spec``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import pandas as pd

from pcrcg.report.spec import LOWER_IS_BETTER, Column, Row, TableSpec
from pcrcg.tracking.git import DEFAULT_IDENTITY, same_code

PAPER_CSV = Path(__file__).resolve().parents[1] / "resources" / "paper_tables.csv"
PAPER_COLUMNS = ("table", "method", "variant", "benchmark", "metric", "n_points", "value")


def load_paper(path: str | Path | None = None) -> pd.DataFrame:
    """The paper's numbers (long format); default: the copy shipped in ``pcrcg/resources``."""
    df = pd.read_csv(path if path is not None else PAPER_CSV, dtype={"variant": str})
    missing = [c for c in PAPER_COLUMNS if c not in df.columns]
    if missing:
        from pcrcg.errors import DataError

        raise DataError(path or "paper_tables.csv", f"missing columns {missing}")
    df["variant"] = df["variant"].fillna("")
    return df


@dataclass(frozen=True)
class RunRef:
    run_id: str
    config_hash: str
    git_sha: str
    profile: str
    seed: str
    seedless: bool = False  # nothing the run computes reads its seed (pcrcg.config.seed_independent)

    def short(self) -> str:
        return (f"run {self.run_id[:8]} · hash {self.config_hash[:8]} · git {self.git_sha[:7]}"
                f" · profile {self.profile} · seed {self.seed}")


@dataclass
class Cell:
    row: Row
    col: Column
    paper: float | None
    mean: float | None = None
    std: float | None = None
    values: list[float] = field(default_factory=list)
    runs: list[RunRef] = field(default_factory=list)
    reason: str | None = None
    metric_key: str | None = None
    keys: list[str] = field(default_factory=list)  # the metric key of each value (aligned with values, runs)

    @property
    def diff(self) -> float | None:
        if self.mean is None or self.paper is None:
            return None
        return self.mean - self.paper

    @property
    def status(self) -> str:
        return "ok" if self.mean is not None else "missing"


@dataclass
class FilledTable:
    spec: TableSpec
    cells: list[Cell]
    profile: str | None
    coverage: dict[str, tuple[float, float, int]] = field(default_factory=dict)  # row text -> (mean, std, n)
    protocol: list[str] = field(default_factory=list)  # settings of the runs behind the cells
    orderings: list[Any] = field(default_factory=list)  # pcrcg.report.orderings.OrderingLine, one per tested ordering
    fidelity: list[str] = field(default_factory=list)  # settings of the runs that differ from the paper's text or code
    identity: str = DEFAULT_IDENTITY  # which runs counted as the same: config_and_code | config
    codes: dict[str, int] = field(default_factory=dict)  # code version -> runs of it behind the cells
    shared: list[str] = field(default_factory=list)  # rows that also count another experiment's runs (same_as)
    machines: dict[str, int] = field(default_factory=dict)  # machine (run_machine) -> runs of it behind the cells

    def identity_text(self) -> str:
        """Which runs a cell counts, and the code versions behind the table."""
        rule = ("same config and code (identity=config_and_code): each cell counts the runs of one code version, "
                "its newest run's" if same_code(self.identity) else
                "same config (identity=config): each cell's seeds may come from different code versions")
        return (f"Runs counted: {rule}; code versions behind the cells: {counted_text(self.codes)}."
                f"{machines_text(self.machines)}")

    def cell(self, row: Row, col: Column) -> Cell:
        for c in self.cells:
            if c.row is row and c.col is col:
                return c
        raise KeyError((row.text, col))


def _text(v: Any) -> str:
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    return str(v)


def match(runs: pd.DataFrame, where: Mapping[str, Any]) -> pd.Series:
    """Boolean mask of runs whose params (else tags) equal ``where``: as text, or as numbers where the filter's
    value is a number (``1.0`` selects a param logged ``1.0`` or ``1``; ``true`` a logged ``True``)."""
    mask = pd.Series(True, index=runs.index)
    for key, value in where.items():
        col = f"params.{key}" if f"params.{key}" in runs.columns else f"tags.{key}"
        if col not in runs.columns:
            return pd.Series(False, index=runs.index)
        logged = runs[col].astype(str)
        same = logged == _text(value)
        if isinstance(value, bool):
            same |= logged.str.lower() == _text(value)
        elif isinstance(value, (int, float)):
            same |= pd.to_numeric(logged, errors="coerce") == float(value)
        mask &= same
    return mask


def _get(rec: Mapping[str, Any], col: str, default: str = "?") -> str:
    v = rec.get(col)
    return default if v is None or (isinstance(v, float) and math.isnan(v)) else str(v)


def _ref(rec: Mapping[str, Any]) -> RunRef:
    return RunRef(str(rec["run_id"]), _get(rec, "tags.config_hash"), _get(rec, "tags.git_sha"),
                  _get(rec, "tags.profile"), _get(rec, "params.seed"), _seedless(rec))


def _seedless(rec: Mapping[str, Any]) -> bool:
    """The run's ``seed_independent`` tag; a run logged before the tag: the same rule on its params."""
    from pcrcg.config import seed_independent

    if _get(rec, "tags.seed_independent", "") == "true":
        return True
    method, init = _get(rec, "params.method", ""), _get(rec, "params.icp_init", "")
    return bool(method and init) and seed_independent({"method": method, "icp_init": init})


PaperKey = tuple[Any, Any, Any, Any, Any, "float | None"]


def paper_values(paper: pd.DataFrame) -> dict[PaperKey, float]:
    """The paper's numbers by (table, method, variant, benchmark, metric, n_points), the first row of each key
    (``n_points`` a float, None where the paper gives none); a key with a missing text field selects nothing."""
    out: dict[PaperKey, float] = {}
    if paper.empty:
        return out
    cols = ["table", "method", "variant", "benchmark", "metric", "n_points", "value"]
    for *text, n, value in paper[cols].itertuples(index=False, name=None):
        if any(v is None or (isinstance(v, float) and math.isnan(v)) for v in text):
            continue
        n = None if n is None or (isinstance(n, float) and math.isnan(n)) else float(n)
        out.setdefault((*text, n), float(value))
    return out


def _paper_value(values: Mapping[PaperKey, float], table: str, row: Row, col: Column) -> float | None:
    variant = col.variant or row.variant
    n = None if col.n_points is None else float(col.n_points)
    return values.get((table, row.method, variant, col.benchmark, col.metric, n))


def run_machine(df: pd.DataFrame) -> pd.Series:
    """Each run's machine: ``<CPU model> (<torch's CPU kernels>)`` and ``+ <CUDA device>`` from its tags
    (:func:`pcrcg.tracking.tracker.machine_tags`); ``unrecorded`` for runs made before those tags."""
    out = pd.Series("unrecorded", index=df.index, dtype=object)
    if "tags.pcrcg.cpu" not in df.columns:
        return out
    none = pd.Series(None, index=df.index, dtype=object)
    cap = df["tags.pcrcg.cpu_capability"] if "tags.pcrcg.cpu_capability" in df.columns else none
    cuda = df["tags.pcrcg.cuda"] if "tags.pcrcg.cuda" in df.columns else none
    for i in df.index:
        cpu = df.at[i, "tags.pcrcg.cpu"]
        if isinstance(cpu, str) and cpu:
            text = cpu + (f" ({cap[i]})" if isinstance(cap[i], str) and cap[i] else "")
            out[i] = text + (f" + {cuda[i]}" if isinstance(cuda[i], str) and cuda[i] else "")
    return out


def run_counts(label: Callable[[pd.DataFrame], pd.Series], runs: pd.DataFrame, used: set[str]) -> dict[str, int]:
    """How many of the runs ``used`` (run ids) carry each label that ``label`` gives (:func:`run_code`,
    :func:`run_machine`)."""
    if not used:
        return {}
    return {str(k): int(n) for k, n in label(runs[runs["run_id"].isin(used)]).value_counts().items()}


def counted_text(counts: Mapping[str, int]) -> str:
    """``A (2 runs), B (1 run)``, or ``none``."""
    return ", ".join(f"{k} ({n} run{'s' if n > 1 else ''})" for k, n in counts.items()) or "none"


def machines_text(machines: Mapping[str, int]) -> str:
    """`` Machines behind them: A (n runs), ...`` (runs of one config and seed differ between CPU types), or
    ``""``."""
    return f" Machines behind them: {counted_text(machines)}." if machines else ""


def run_code(df: pd.DataFrame) -> pd.Series:
    """Each run's code: its ``code_version`` tag; a run recorded before that tag, ``git <sha>`` (``+dirty``
    when its tree had uncommitted changes); ``unrecorded`` without either."""
    code = pd.Series("unrecorded", index=df.index, dtype=object)
    if "tags.git_sha" in df.columns:
        dirty = df["tags.git_dirty"] if "tags.git_dirty" in df.columns else pd.Series("false", index=df.index)
        git = "git " + df["tags.git_sha"].astype(str).str[:7] + dirty.map(lambda d: "+dirty" if d == "true" else "")
        code = code.where(df["tags.git_sha"].isna(), git)
    if "tags.code_version" in df.columns:
        code = code.where(df["tags.code_version"].isna(), df["tags.code_version"])
    return code


def _newest_per_seed(df: pd.DataFrame, identity: str = DEFAULT_IDENTITY) -> pd.DataFrame:
    """One run per seed: the newest (a config that changed since keeps only its latest run); under
    ``config_and_code`` only among the runs of the newest run's code version."""
    key = "params.seed" if "params.seed" in df.columns else "tags.config_hash"
    if df.empty or key not in df.columns:
        return df
    if same_code(identity):
        code = run_code(df)
        df = df[code == code.loc[df["start_time"].idxmax()]]
    return df.sort_values("start_time").groupby(key, dropna=False, sort=False).tail(1)


def _where_text(where: Mapping[str, Any]) -> str:
    return ", ".join(f"{k}={_text(v)}" for k, v in where.items()) or "any config"


def _missing_reason(candidates: pd.DataFrame, experiment: str, where: Mapping[str, Any], profile: str | None,
                    row: Row | None = None) -> str:
    if not candidates.empty:
        last = candidates.sort_values("start_time").iloc[-1]
        status = str(last["status"])
        error = _get(last, "tags.error", "")
        if status == "FAILED":
            kind = "not run" if _get(last, "tags.not_run", "") == "true" else "failed"
            return f"{kind}: {error or 'no error recorded'} (run {str(last['run_id'])[:8]})"
        if status in ("RUNNING", "SCHEDULED"):
            return f"still running or crashed (run {str(last['run_id'])[:8]})"
        return f"{status.lower()} (run {str(last['run_id'])[:8]})"
    prof = f" at profile {profile}" if profile else ""
    how = f" (not in the sweep: {row.command(experiment, profile)})" if row is not None and row.job else ""
    return f"no run of experiment '{experiment}' with {_where_text(where)}{prof}{how}"


def _no_value_reason(done: pd.DataFrame, col: Column) -> str:
    sizes = set(_values(done, "params.eval.n_points"))
    if col.n_points is not None and sizes:
        import json

        evaluated = {n for text in sizes for n in json.loads(text)}
        if col.n_points not in evaluated:
            return f"not evaluated at {col.n_points} points (eval.n_points={'/'.join(sorted(sizes))})"
    return (f"no value of {' or '.join(col.keys())} in {len(done)} finished run(s) "
            f"(not logged, or NaN: e.g. RRE when no pair registered)")


def fill_table(spec: TableSpec, runs: pd.DataFrame, paper: pd.DataFrame,
               profiles: Mapping[str, str | None], identity: str = DEFAULT_IDENTITY) -> FilledTable:
    """Every cell of ``spec`` from ``runs`` (see module docstring).

    ``profiles``: experiment -> the profile whose runs count (None: any). ``identity``: ``config_and_code``
    or ``config`` (module docstring).
    """
    cells: list[Cell] = []
    coverage: dict[str, tuple[float, float, int]] = {}
    shared: list[str] = []
    paper_at = paper_values(paper)
    by_experiment: dict[tuple[str, str | None], pd.DataFrame] = {}

    def experiment_runs(experiment: str, profile: str | None) -> pd.DataFrame:
        if (experiment, profile) not in by_experiment:
            by_experiment[experiment, profile] = _experiment_runs(runs, experiment, profile)
        return by_experiment[experiment, profile]

    for row in spec.rows:
        exp = row.experiment or spec.experiment
        prof = profiles.get(exp)
        base = experiment_runs(exp, prof)
        row_runs = base[match(base, row.where)] if row.where else (base.iloc[0:0] if row.reason else base)
        if row.same_as is not None and row.where:
            other = experiment_runs(row.same_as.experiment, profiles.get(row.same_as.experiment, prof))
            other = other[match(other, {**row.where, **row.same_as.where})]
            if not other.empty:
                row_runs = pd.concat([row_runs, other])
            n_other = int((other["status"] == "FINISHED").sum()) if "status" in other.columns else 0
            shared.append(f"{row.text}: also the runs of {row.same_as.text} ({n_other} finished), the same config")
        for col in spec.columns:
            cell = Cell(row, col, _paper_value(paper_at, spec.paper_table, row, col))
            cells.append(cell)
            if row.reason and not row.where:
                cell.reason = row.reason
                continue
            cand = row_runs[match(row_runs, col.where)] if col.where else row_runs
            done = _newest_per_seed(cand[cand["status"] == "FINISHED"], identity)
            if done.empty:
                cell.reason = row.reason or _missing_reason(cand, exp, {**row.where, **col.where}, prof, row)
                if cand.empty and row.same_as is not None and not row.reason:
                    cell.reason += f"; nor of {row.same_as.text}"
                continue
            vals, refs, keys = [], [], []
            records = done.to_dict("records")  # (not iterrows: a Series per row of a wide frame is slow)
            for rec in records:
                for key in col.keys():
                    v = rec.get(f"metrics.{key}")
                    if v is not None and not (isinstance(v, float) and math.isnan(v)):
                        vals.append(float(v))
                        refs.append(_ref(rec))
                        keys.append(key)
                        cell.metric_key = key
                        break
            cell.runs = refs
            cell.keys = keys
            if not vals:
                # (MLflow's table shows a metric that was not logged and a NaN alike)
                cell.runs = [_ref(rec) for rec in records]
                cell.reason = _no_value_reason(done, col)
                continue
            cell.values = vals
            cell.mean = float(np.mean(vals))
            cell.std = float(np.std(vals, ddof=1)) if len(vals) > 1 else 0.0
        cov_col = "metrics.color_coverage"
        if cov_col in row_runs.columns:
            done = _newest_per_seed(row_runs[row_runs["status"] == "FINISHED"], identity)
            vals = [float(v) for v in done[cov_col] if v is not None and not math.isnan(float(v))]
            if vals:
                coverage[row.text] = (float(np.mean(vals)), float(np.std(vals, ddof=1)) if len(vals) > 1 else 0.0,
                                      len(vals))
    used = {r.run_id for c in cells for r in c.runs}
    proto = protocol_summary(runs[runs["run_id"].isin(used)]) if used else []
    from pcrcg.report.fidelity import fidelity_lines

    fidelity = fidelity_lines(runs[runs["run_id"].isin(used)]) if used else []
    return FilledTable(spec, cells, profiles.get(spec.experiment), coverage, proto, fidelity=fidelity,
                       identity=identity, codes=run_counts(run_code, runs, used), shared=shared,
                       machines=run_counts(run_machine, runs, used))


def _experiment_runs(runs: pd.DataFrame, experiment: str, profile: str | None) -> pd.DataFrame:
    """The runs of ``experiment`` (of ``profile`` when given)."""
    base = runs[runs["experiment"] == experiment] if "experiment" in runs.columns else runs.iloc[0:0]
    if profile is not None and "tags.profile" in base.columns:
        base = base[base["tags.profile"].astype(str) == profile]
    return base


def _values(df: pd.DataFrame, col: str) -> list[str]:
    if col not in df.columns:
        return []
    vals = df[col].dropna().astype(str).unique().tolist()
    return sorted(vals, key=lambda s: (len(s), s))


# the facts worth a line under each table (pcrcg.evaluation's protocol dict); all are in the CSV/MLflow
_PROTOCOL_KEYS = ("pairs", "pairs_counted_in_rr", "n_pairs", "n_pairs_rr", "ransac.max_iterations", "ransac.distance",
                  "ransac_budget", "sampling", "fewer_points", "predator_variant", "seed")


def protocol_summary(runs: pd.DataFrame) -> list[str]:
    """Short facts about how ``runs`` were evaluated: pairs per benchmark, RANSAC, seeds, profile."""
    if runs.empty:
        return []
    out = []
    benches = sorted({c.split(".")[2] for c in runs.columns
                      if c.startswith("params.protocol.") and c.count(".") >= 3})
    for b in benches:
        pre = f"params.protocol.{b}."
        keys = [k for k in _PROTOCOL_KEYS if _values(runs, pre + k)]
        if not keys:  # unknown layout: every plain (not nested) fact
            keys = [c[len(pre):] for c in sorted(runs.columns) if c.startswith(pre) and "." not in c[len(pre):]]
        facts = [f"{k} {'/'.join(_values(runs, pre + k))}" for k in keys if _values(runs, pre + k)]
        if facts:
            out.append(f"{b}: " + ", ".join(facts))
    ransac = [f"{c.split('ransac_')[-1].split('.')[-1]} {'/'.join(_values(runs, c))}"
              for c in sorted(runs.columns) if c.startswith("params.eval.ransac_") and _values(runs, c)]
    if ransac and "ransac" not in benches and not any("ransac" in line for line in out):
        out.append("RANSAC " + ", ".join(ransac))
    seeds = _values(runs, "params.seed")
    if seeds:
        out.append("seeds " + ", ".join(seeds))
    return out


def trend_agreement(table: FilledTable) -> dict[str, Any]:
    """How well our row ordering follows the paper's, per column, over rows with both numbers.

    Returns ``{"pairs": n, "agree": k, "fraction": k / n, "best_paper": {...}, "best_ours": {...},
    "orderings": {...}}`` (best row per column; lower is better for RRE/RTE). ``orderings``: of
    the paper's orderings the report tests (``table.orderings``), how many hold beyond the paired
    bootstrap interval, are reversed beyond it, lie within noise, or could not be tested
    (``untested``: no interval; ``no_ordering``: a tie or no numbers in the paper).
    """
    agree = pairs = 0
    best_paper: dict[str, str] = {}
    best_ours: dict[str, str] = {}
    for col in table.spec.columns:
        both = [c for c in table.cells if c.col is col and c.mean is not None and c.paper is not None]
        sign = -1.0 if col.metric in LOWER_IS_BETTER else 1.0
        key = f"{col.benchmark} {col.metric} {col.n_points or ''}".strip()
        if both:
            best_paper[key] = max(both, key=lambda c: sign * c.paper).row.text  # type: ignore[operator]
            best_ours[key] = max(both, key=lambda c: sign * c.mean).row.text  # type: ignore[operator]
        for i in range(len(both)):
            for j in range(i + 1, len(both)):
                dp = both[i].paper - both[j].paper  # type: ignore[operator]
                do = both[i].mean - both[j].mean  # type: ignore[operator]
                if dp == 0:
                    continue
                pairs += 1
                agree += int(np.sign(dp) == np.sign(do))
    from pcrcg.report.stats import HOLDS, NO_PAPER, NOISE, PAPER_TIE, REVERSED

    counts = {"tested": 0, "holds": 0, "reversed": 0, "within_noise": 0, "untested": 0, "no_ordering": 0}
    for line in table.orderings:
        v = line.verdict
        if v in (NO_PAPER, PAPER_TIE):
            counts["no_ordering"] += 1
        elif v is None:
            counts["untested"] += 1
        else:
            counts["tested"] += 1
            counts[{HOLDS: "holds", REVERSED: "reversed", NOISE: "within_noise"}[v]] += 1
    return {"pairs": pairs, "agree": agree, "fraction": agree / pairs if pairs else float("nan"),
            "best_paper": best_paper, "best_ours": best_ours, "orderings": counts}
