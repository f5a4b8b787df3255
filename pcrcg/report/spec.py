"""Table specifications: which runs fill which cell of a paper table.

A table (``conf/report.yaml``, ``specs.<name>``) has rows and columns. A cell is the pair
(row, column); its runs are the FINISHED runs of the row's experiment that match both the
row's and the column's ``where`` filters (flattened-config params or tags, compared as
text), and its paper number is the entry of ``paper_tables.csv`` with the table's
``paper_table`` name, the row's method, the variant of the row or column, and the
column's benchmark, metric and sample size.

Columns are listed explicitly or as a ``grid`` (metric x benchmark x n_points, in that
order); the metric also names the table's sections in Markdown/LaTeX.

``compare`` names the orderings of the paper that the report tests (``pcrcg.report.orderings``):
``consecutive`` (each row against the one above it), ``{baseline: <row>}`` (every row against
one), ``{pairs: [[<reference row>, <row>], ...]}`` and ``{columns: [[<reference variant>,
<variant>], ...]}`` (within each row, e.g. ICP from the original vs. the improved pose); keys
combine. A row is named by its label, its ``method variant`` text, its variant or its method
(whichever is unique). Only rows with runs of ours take part (published baselines do not).

``same_as: {experiment: <name>, where: {...}, job: <overrides>}`` on a row: that experiment runs the row's config too (the
window table's 11x11 row is ``main_results``' PCR-CG run; the views table's 2-view row is the projection
table's Pri3D/implicit run). Its runs that match the row's ``where`` and its own ``where`` count in the row's
cells beside the row's own, newest per seed; the report names the borrowed experiment under the table, and
``tests/test_report_rows.py`` checks that both experiments' jobs have one config hash. A sweep (or the
findings' job list) then need not run one config twice.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from pcrcg.errors import ConfigError

# paper metric name -> our metric key templates, tried in order ({b}: benchmark, {n}: sample size)
METRIC_KEYS: dict[str, tuple[str, ...]] = {
    "RR": ("{b}/rr_{n}",),
    "FMR": ("{b}/fmr_{n}",),
    "IR": ("{b}/ir_{n}",),
    "RRE_deg": ("{b}/rre_{n}", "{b}/rre"),
    "RTE_m": ("{b}/rte_{n}", "{b}/rte"),
}
# without a sample size (icp_init, sift_dlt, geotransformer): the method's own recall, else the one at 5000 points
# (a model that registers pairs itself, GeoTransformer's LGR: its own estimate's metrics, ``_lgr``)
METRIC_KEYS_NO_N: dict[str, tuple[str, ...]] = {
    "RR": ("{b}/rr", "{b}/rr_lgr", "{b}/rr_5000"),
    "FMR": ("{b}/fmr", "{b}/fmr_lgr", "{b}/fmr_5000"),
    "IR": ("{b}/ir", "{b}/ir_lgr", "{b}/ir_5000"),
    "RRE_deg": ("{b}/rre_lgr", "{b}/rre"),
    "RTE_m": ("{b}/rte_lgr", "{b}/rte"),
}
METRIC_TITLES = {
    "RR": "Registration Recall (%)",
    "FMR": "Feature Matching Recall (%)",
    "IR": "Inlier Ratio (%)",
    "RRE_deg": "RRE (deg)",
    "RTE_m": "RTE (m)",
}
# lower is better for these (the sign of "better" in the difference)
LOWER_IS_BETTER = ("RRE_deg", "RTE_m")


def run_command(experiment: str, job: str | None = None, profile: str | None = None,
                seeds: Sequence[int] = ()) -> str:
    """``python -m pcrcg.run +experiment=<experiment> <job> [profile=..] [seed=a,b -m]``: the command that
    runs one job of an experiment (``default``: the main job, without an experiment file)."""
    parts = ["python -m pcrcg.run", "" if experiment == "default" else f"+experiment={experiment}", job or "",
             f"profile={profile}" if profile else "", f"seed={','.join(str(s) for s in seeds)} -m" if seeds else ""]
    return " ".join(p for p in parts if p)


@dataclass(frozen=True)
class SameAs:
    """Another experiment whose runs matching ``where`` (and the row's own filter) are the row's config."""

    experiment: str
    where: Mapping[str, Any] = field(default_factory=dict)
    job: str | None = None  # the overrides that make those runs when that experiment's sweep does not

    @property
    def text(self) -> str:
        cond = ", ".join(f"{k}={v}" for k, v in self.where.items())
        return f"experiment '{self.experiment}'" + (f" ({cond})" if cond else "")


@dataclass(frozen=True)
class Row:
    method: str
    variant: str = ""
    label: str = ""
    where: Mapping[str, Any] = field(default_factory=dict)
    experiment: str | None = None
    reason: str | None = None  # why this row has no runs by design (e.g. a published baseline)
    job: str | None = None  # overrides beyond the experiment's sweep that make this row's runs (a job of its own)
    same_as: SameAs | None = None  # another experiment that runs this row's config (its runs count too)

    @property
    def text(self) -> str:
        return self.label or (f"{self.method} {self.variant}".strip())

    def command(self, experiment: str, profile: str | None = None) -> str:
        """The command that makes this row's runs when the experiment's sweep does not (``job``)."""
        return run_command(experiment, self.job, profile)


@dataclass(frozen=True)
class Column:
    benchmark: str
    metric: str
    n_points: int | None = None
    variant: str = ""
    label: str = ""
    where: Mapping[str, Any] = field(default_factory=dict)

    @property
    def section(self) -> str:
        return METRIC_TITLES.get(self.metric, self.metric)

    def keys(self) -> tuple[str, ...]:
        templates = METRIC_KEYS if self.n_points is not None else METRIC_KEYS_NO_N
        if self.metric not in templates:
            raise ConfigError("report column metric", self.metric, ", ".join(templates))
        return tuple(t.format(b=self.benchmark, n=self.n_points) for t in templates[self.metric])


@dataclass(frozen=True)
class Comparison:
    """Two cells per column compared as ``row − ref``: two rows (same columns), or, with
    ``ref_variant``/``variant`` set, two column variants of the same row."""

    ref: Row
    row: Row
    ref_variant: str | None = None
    variant: str | None = None

    @property
    def text(self) -> str:
        if self.variant is not None:
            return f"{self.row.text}: {self.variant} − {self.ref_variant}"
        return f"{self.row.text} − {self.ref.text}"


@dataclass(frozen=True)
class TableSpec:
    name: str
    title: str
    experiment: str
    rows: tuple[Row, ...]
    columns: tuple[Column, ...]
    paper_table: str = ""
    note: str = ""
    compare: tuple[Comparison, ...] = ()

    @property
    def experiments(self) -> list[str]:
        """The experiments whose runs the table reads, each once: its own, its rows', their ``same_as``."""
        rows = [r.experiment for r in self.rows if r.experiment]
        shared = [r.same_as.experiment for r in self.rows if r.same_as]
        return list(dict.fromkeys([self.experiment] + rows + shared))


def _columns(raw: Mapping[str, Any] | Sequence[Mapping[str, Any]], table: str) -> tuple[Column, ...]:
    if isinstance(raw, Mapping) and "metric" in raw:  # grid
        metrics = list(raw["metric"])
        benches = list(raw["benchmark"])
        ns = list(raw.get("n_points") or [None])
        return tuple(Column(b, m, None if n is None else int(n)) for m in metrics for b in benches for n in ns)
    cols = []
    for c in raw:  # type: ignore[union-attr]
        n = c.get("n_points")
        cols.append(Column(str(c["benchmark"]), str(c["metric"]), None if n is None else int(n),
                           str(c.get("variant") or ""), str(c.get("label") or ""), dict(c.get("where") or {})))
    if not cols:
        raise ConfigError(f"specs.{table}.columns", raw, "a grid {metric, benchmark, n_points} or a list of columns")
    return tuple(cols)


def _find_row(rows: Sequence[Row], name: Any, where: str) -> Row:
    name = str(name)
    for attr in ("label", "text", "variant", "method"):
        hits = [r for r in rows if getattr(r, attr) == name]
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1 and attr in ("label", "text"):
            break
    raise ConfigError(where, name, "a unique row label, 'method variant', variant or method of the table: "
                      + ", ".join(repr(r.text) for r in rows))


def _pair(item: Any, where: str) -> tuple[Any, Any]:
    if isinstance(item, (list, tuple)) and len(item) == 2:
        return item[0], item[1]
    raise ConfigError(where, item, "a pair [reference, compared]")


def parse_compare(raw: Any, rows: Sequence[Row], columns: Sequence[Column], table: str) -> tuple[Comparison, ...]:
    """The ``compare`` node of a table spec -> comparisons (see module docstring)."""
    if raw in (None, "", False, "none"):
        return ()
    where = f"specs.{table}.compare"
    node = {"consecutive": True} if raw == "consecutive" else raw
    if not isinstance(node, Mapping):
        raise ConfigError(where, raw, "consecutive, or a mapping of consecutive / baseline / pairs / columns")
    unknown = set(node) - {"consecutive", "baseline", "pairs", "columns"}
    if unknown:
        raise ConfigError(where, sorted(unknown), "consecutive, baseline, pairs, columns")
    ours = [r for r in rows if r.where]
    out: list[Comparison] = []
    if node.get("consecutive"):
        out += [Comparison(a, b) for a, b in zip(ours, ours[1:])]
    if node.get("baseline") is not None:
        ref = _find_row(rows, node["baseline"], f"{where}.baseline")
        out += [Comparison(ref, r) for r in ours if r is not ref]
    for item in node.get("pairs") or []:
        a, b = _pair(item, f"{where}.pairs")
        out.append(Comparison(_find_row(rows, a, f"{where}.pairs"), _find_row(rows, b, f"{where}.pairs")))
    variants = {c.variant for c in columns}
    for item in node.get("columns") or []:
        va, vb = (str(v) for v in _pair(item, f"{where}.columns"))
        for v in (va, vb):
            if v not in variants:
                raise ConfigError(f"{where}.columns", v, "a column variant of the table: " + ", ".join(sorted(variants)))
        out += [Comparison(r, r, va, vb) for r in ours]
    seen, unique = set(), []
    for c in out:
        key = (id(c.ref), id(c.row), c.ref_variant, c.variant)
        if key in seen or (c.ref is c.row and c.variant is None):  # twice, or a row against itself
            continue
        seen.add(key)
        unique.append(c)
    return tuple(unique)


def _same_as(raw: Any, where: str) -> SameAs | None:
    if raw is None:
        return None
    if not isinstance(raw, Mapping) or not isinstance(raw.get("experiment"), str) \
            or set(raw) - {"experiment", "where", "job"} or not isinstance(raw.get("where") or {}, Mapping):
        raise ConfigError(where, raw, "{experiment: <name>, where: {key: value, ...}, job: <overrides, optional>}")
    return SameAs(raw["experiment"], dict(raw.get("where") or {}), raw.get("job"))


def default_where(node: Mapping[str, Any] | None) -> dict[str, Any]:
    """The report's ``where`` (conf/report.yaml: nested, ``{registration: {ransac: {score: overlap}}}``) as the
    flat filters of a row (``{"registration.ransac.score": "overlap"}``); None or empty: no filter."""
    if node is None:
        return {}
    if not isinstance(node, Mapping):
        raise ConfigError("where", node, "a mapping of config keys to values, e.g. {registration: {ransac: {score: overlap}}}")
    out: dict[str, Any] = {}
    for key, value in node.items():
        if isinstance(value, Mapping):
            out.update({f"{key}.{k}": v for k, v in default_where(value).items()})
        else:
            out[str(key)] = value
    return out


def report_where(cfg: Any) -> dict[str, Any]:
    """The flat filters of a loaded report config's ``where`` (an OmegaConf node or a mapping; absent: none)."""
    from omegaconf import OmegaConf

    node = cfg.get("where")
    return default_where(OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node)


def with_defaults(where: Mapping[str, Any], defaults: Mapping[str, Any]) -> dict[str, Any]:
    """``where`` with each of the report's default filters it does not set itself (a row's own value wins)."""
    return {**where, **{k: v for k, v in defaults.items() if k not in where}}


def parse_specs(raw: Mapping[str, Any], defaults: Mapping[str, Any] | None = None) -> dict[str, TableSpec]:
    """``specs`` node of conf/report.yaml -> {name: TableSpec}. ``defaults``: flat filters every row of ours
    inherits unless it sets the key (:func:`default_where`); a published baseline (a row without ``where``)
    stays without runs."""
    out: dict[str, TableSpec] = {}
    for name, s in raw.items():
        rows = tuple(
            Row(method=str(r["method"]), variant=str(r.get("variant") or ""), label=str(r.get("label") or ""),
                where=with_defaults(r["where"], defaults or {}) if r.get("where") else {},
                experiment=r.get("experiment"), reason=r.get("reason"),
                job=r.get("job"), same_as=_same_as(r.get("same_as"), f"specs.{name}.rows[{i}].same_as"))
            for i, r in enumerate(s["rows"])
        )
        if not rows:
            raise ConfigError(f"specs.{name}.rows", [], "at least one row")
        columns = _columns(s["columns"], name)
        out[name] = TableSpec(
            name=name,
            title=str(s.get("title", name)),
            experiment=str(s.get("experiment", name)),
            rows=rows,
            columns=columns,
            paper_table=str(s.get("paper_table", name)),
            note=str(s.get("note", "") or ""),
            compare=parse_compare(s.get("compare"), rows, columns, name),
        )
    return out
