"""The paper's orderings between rows, tested beyond test-pair noise.

For each comparison of a table (``compare`` in ``conf/report.yaml``, :class:`~pcrcg.report.spec.Comparison`),
each recall metric and benchmark of its columns, and each place of ``stats.at`` (a sample size
such as 5000, and ``mean``: the mean over the table's sample sizes; tables without sample sizes
have one place), one :class:`OrderingLine`:

* the paper's difference ``row − reference`` (from ``paper_tables.csv``; the mean over the
  sizes for ``mean``);
* ours: the difference of our means over seeds, ``± std`` over seeds where both rows ran the
  same two or more seeds (the per-seed difference);
* the paired bootstrap interval (:mod:`pcrcg.report.stats`) over the test pairs, from the runs'
  per-pair outcomes (:mod:`pcrcg.report.outcomes`); for ``mean`` a pair's outcome is its mean
  over the sizes (the statistic is linear, so this is the mean over sizes of the recalls);
  with several seeds, seed is compared with seed: where the two rows share seeds only the shared seeds
  count (means and interval), and the bootstrap draws seeds (the same for both rows), then pairs
  (``stats.seeds: resample``, :mod:`pcrcg.report.stats`), so that seeds that disagree widen the interval;
  ``stats.seeds: pool`` averages each row's seeds per pair and resamples pairs only;
* the verdict: ``holds`` (the interval excludes 0 on the paper's side), ``reversed`` (on the
  other side), ``within noise``, or no ordering to test (a tie or no numbers in the paper);
  ``None`` with a reason when there is no interval.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np

from pcrcg.errors import ConfigError
from pcrcg.report.spec import Column, Comparison
from pcrcg.report.stats import LEVEL, N_BOOT, SEED, SEED_MODES, Interval, mean_std, paired_bootstrap, verdict
from pcrcg.report.tables import Cell, FilledTable

MEAN = "mean"
# metrics with a per-pair outcome (the others, RRE/RTE/IR, are not tested)
TESTED_METRICS = ("RR", "FMR")


@dataclass(frozen=True)
class StatsSettings:
    """``stats`` node of conf/report.yaml."""

    n_boot: int = N_BOOT
    seed: int = SEED
    level: float = LEVEL
    at: tuple[Any, ...] = (5000, MEAN)
    metrics: tuple[str, ...] = TESTED_METRICS
    seeds: str = "resample"  # resample: seeds, then pairs; pool: seeds averaged per pair, pairs resampled

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "StatsSettings":
        d = dict(d or {})
        at = tuple(MEAN if str(a) == MEAN else _number(int, "stats.at", a, f"sample sizes or {MEAN!r}")
                   for a in (d.get("at") or cls.at))
        metrics = tuple(str(m) for m in (d.get("metrics") or cls.metrics))
        bad = [m for m in metrics if m not in TESTED_METRICS]
        if bad:
            raise ConfigError("stats.metrics", bad, " | ".join(TESTED_METRICS))
        level = _number(float, "stats.level", d.get("level", cls.level), "a number in (0, 1), e.g. 0.95")
        if not 0 < level < 1:
            raise ConfigError("stats.level", level, "a number in (0, 1), e.g. 0.95")
        n_boot = _number(int, "stats.n_boot", d.get("n_boot", cls.n_boot), "a positive number of resamples, e.g. 2000")
        if n_boot < 1:
            raise ConfigError("stats.n_boot", n_boot, "a positive number of resamples, e.g. 2000")
        seed = _number(int, "stats.seed", d.get("seed", cls.seed), "an integer")
        seeds = d.get("seeds", cls.seeds)
        if seeds not in SEED_MODES:
            raise ConfigError("stats.seeds", seeds, " | ".join(SEED_MODES))
        return cls(n_boot, seed, level, at, metrics, seeds)


def _number(kind: type, setting: str, value: Any, allowed: str) -> Any:
    """``kind(value)`` (int or float; not a bool), or a ConfigError naming ``setting``."""
    try:
        if isinstance(value, bool):
            raise ValueError(value)
        return kind(value)
    except (TypeError, ValueError):
        raise ConfigError(setting, value, allowed) from None


@dataclass
class OrderingLine:
    comparison: Comparison
    metric: str
    benchmark: str
    variant: str
    at: int | str | None
    paper_ref: float | None = None
    paper_row: float | None = None
    ours_ref: float | None = None
    ours_row: float | None = None
    ours_diff: float | None = None
    ours_std: float | None = None
    n_seeds: int = 0  # seeds both rows ran (behind ours_std)
    by_seed: dict[str, float] = field(default_factory=dict)  # seed -> row − ref of that seed's runs (seeds both ran)
    interval: Interval | None = None
    verdict: str | None = None
    reason: str | None = None
    source: str = ""
    ref_runs: list[str] = field(default_factory=list)
    row_runs: list[str] = field(default_factory=list)

    @property
    def paper_diff(self) -> float | None:
        if self.paper_ref is None or self.paper_row is None:
            return None
        return self.paper_row - self.paper_ref

    @property
    def where(self) -> str:
        at = "" if self.at is None else ("mean over N" if self.at == MEAN else f"{self.at}")
        variant = self.variant if self.variant and self.comparison.variant is None else ""
        return " ".join(p for p in (variant, self.benchmark, self.metric, at) if p)


def _groups(columns: Sequence[Column]) -> dict[tuple[str, str, str], list[Column]]:
    out: dict[tuple[str, str, str], list[Column]] = {}
    for c in columns:
        out.setdefault((c.metric, c.benchmark, c.variant), []).append(c)
    return out


def select_columns(cols: Sequence[Column], at: Any) -> list[Column]:
    """The columns of the place ``at``: its sample size, every size for the mean over N, the unsized one for None."""
    if at is None:
        return [c for c in cols if c.n_points is None][:1]
    if at == MEAN:
        sized = [c for c in cols if c.n_points is not None]
        return sized if len(sized) > 1 else []
    return [c for c in cols if c.n_points == at]


def _places(cols: Sequence[Column], settings: StatsSettings) -> list[Any]:
    if all(c.n_points is None for c in cols):
        return [None]
    return [a for a in settings.at if select_columns(cols, a)]


def _mean(vals: Sequence[float | None]) -> float | None:
    return float(np.mean(vals)) if vals and all(v is not None for v in vals) else None


def _per_run(cells: Sequence[Cell]) -> dict[str, tuple[Any, float, list[tuple[str, float]]]]:
    """run id -> (RunRef, mean value over the cells, [(metric key, value) per cell]) for the runs in every cell."""
    by_cell = [{r.run_id: (r, k, v) for r, k, v in zip(c.runs, c.keys, c.values)} for c in cells]
    common = [rid for rid in by_cell[0] if all(rid in d for d in by_cell[1:])] if by_cell else []
    out = {}
    for rid in common:
        kv = [(d[rid][1], d[rid][2]) for d in by_cell]
        out[rid] = (by_cell[0][rid][0], float(np.mean([v for _, v in kv])), kv)
    return out


def _broadcast(ref_runs: dict, row_runs: dict) -> tuple[dict, dict]:
    """A side whose runs do not depend on the seed (``RunRef.seedless``: ICP from the identity) stands for every
    seed of the other side: its newest run, once per seed (keys ``<run id>#<seed>``), so that the other side's
    seeds are all compared, seed against the same run."""
    def seedless(runs: dict) -> bool:
        return bool(runs) and all(v[0].seedless for v in runs.values())

    def spread(runs: dict, seeds: list[str]) -> dict:
        ref, value, kv = list(runs.values())[-1]
        return {f"{ref.run_id}#{s}": (replace(ref, seed=s), value, kv) for s in seeds}

    if seedless(ref_runs) and row_runs and not seedless(row_runs):
        return spread(ref_runs, [v[0].seed for v in row_runs.values()]), row_runs
    if seedless(row_runs) and ref_runs and not seedless(ref_runs):
        return ref_runs, spread(row_runs, [v[0].seed for v in ref_runs.values()])
    return ref_runs, row_runs


def _seeds_in_order(runs: dict, seeds: set[str]) -> dict:
    """The runs of ``seeds``, in seed order."""
    return {k: v for k, v in sorted(runs.items(), key=lambda kv: _seed_key(kv[1][0].seed)) if v[0].seed in seeds}


def _seed_key(seed: str) -> tuple[int, float, str]:
    """Seeds in numeric order where they are numbers (``"2"`` before ``"10"``), else as text."""
    try:
        return (0, float(seed), "")
    except ValueError:
        return (1, 0.0, str(seed))


def _missing(cells: Sequence[Cell]) -> str:
    for c in cells:
        if c.mean is None:
            return f"{c.row.text}: {c.reason or 'no number of ours'}"
    return "no run of ours is in every column compared"


def _vector(source: Any, rid: str, kv: Sequence[tuple[str, float]]):
    """A run's per-pair outcome, averaged over the cells (sample sizes); (series, source) or (None, reason)."""
    series, where = [], ""
    for key, value in kv:
        o = source.outcomes(rid, key, value)
        if o.values is None:
            return None, o.reason
        series.append(o.values)
        where = o.source
    first = series[0]
    for s in series[1:]:
        if not s.index.equals(first.index):
            return None, f"run {rid[:8]}: the sample sizes were scored on different pairs"
    return (first if len(series) == 1 else sum(series[1:], first) / len(series)), where


def compare_columns(table: FilledTable, comp: Comparison, metric: str, bench: str, variant: str, at: Any,
                    ref_cols: Sequence[Column], row_cols: Sequence[Column], source: Any,
                    settings: StatsSettings) -> OrderingLine:
    """One line: ``comp.row`` at ``row_cols`` against ``comp.ref`` at ``ref_cols`` (the same length; each
    side's mean over its columns), at the place ``at`` (see module docstring)."""
    ref_cells = [table.cell(comp.ref, c) for c in ref_cols]
    row_cells = [table.cell(comp.row, c) for c in row_cols]
    line = OrderingLine(comp, metric, bench, variant, at,
                        paper_ref=_mean([c.paper for c in ref_cells]), paper_row=_mean([c.paper for c in row_cells]))
    ref_runs, row_runs = _broadcast(_per_run(ref_cells), _per_run(row_cells))
    both = {r.seed for r, _, _ in ref_runs.values()} & {r.seed for r, _, _ in row_runs.values()}
    if both:  # compare seed with seed: only the seeds both rows ran, in the same order on both sides
        ref_runs, row_runs = _seeds_in_order(ref_runs, both), _seeds_in_order(row_runs, both)
    line.ref_runs = list(dict.fromkeys(v[0].run_id for v in ref_runs.values()))
    line.row_runs = list(dict.fromkeys(v[0].run_id for v in row_runs.values()))
    if not ref_runs or not row_runs:
        line.reason = _missing(ref_cells if not ref_runs else row_cells)
        line.verdict = verdict(line.paper_diff, None)
        return line
    line.ours_ref = float(np.mean([v for _, v, _ in ref_runs.values()]))
    line.ours_row = float(np.mean([v for _, v, _ in row_runs.values()]))
    line.ours_diff = line.ours_row - line.ours_ref
    by_seed_ref = {r.seed: v for r, v, _ in ref_runs.values()}
    by_seed_row = {r.seed: v for r, v, _ in row_runs.values()}
    common = [s for s in by_seed_row if s in by_seed_ref]
    line.by_seed = {s: by_seed_row[s] - by_seed_ref[s] for s in common}
    if len(common) > 1:
        _, line.ours_std, line.n_seeds = mean_std(list(line.by_seed.values()))
    if source is None:
        line.reason = "per-pair outcomes were not loaded"
    else:
        vecs: dict[str, list] = {"ref": [], "row": []}
        wheres: list[str] = []
        loaded: dict[str, tuple] = {}  # a run that stands for several seeds (_broadcast) is read once
        for side, runs in (("ref", ref_runs), ("row", row_runs)):
            for ref, _, kv in runs.values():
                if ref.run_id not in loaded:
                    loaded[ref.run_id] = _vector(source, ref.run_id, kv)
                s, where = loaded[ref.run_id]
                if s is None:
                    line.reason = where
                    break
                vecs[side].append(s)
                wheres.append(where)
            if line.reason:
                break
        if not line.reason:
            first = vecs["ref"][0]
            if not all(s.index.equals(first.index) for s in vecs["ref"] + vecs["row"]):
                line.reason = ("the runs compared were scored on different test pairs (data set or evaluation "
                               "settings differ), so no paired interval")
            else:
                matched = [r.seed for r, _, _ in ref_runs.values()] == [r.seed for r, _, _ in row_runs.values()]
                line.interval = paired_bootstrap(
                    np.stack([s.to_numpy() for s in vecs["ref"]]), np.stack([s.to_numpy() for s in vecs["row"]]),
                    first.index.get_level_values("scene"), n_boot=settings.n_boot, seed=settings.seed,
                    level=settings.level, seeds=settings.seeds if matched else "pool")
                line.ours_diff = line.interval.diff
                line.source = "; ".join(dict.fromkeys(wheres))
    line.verdict = verdict(line.paper_diff, line.interval)
    return line


def check_orderings(table: FilledTable, source: Any, settings: StatsSettings | None = None,
                    keep_empty: bool = False) -> list[OrderingLine]:
    """Every tested ordering of ``table`` (see module docstring). ``source``: an
    :class:`~pcrcg.report.outcomes.OutcomeSource` (None: no intervals). ``keep_empty``: also the lines
    that neither the paper nor we can fill (the findings table says why each is missing)."""
    settings = settings or StatsSettings()
    groups = _groups(table.spec.columns)
    lines: list[OrderingLine] = []
    for comp in table.spec.compare:
        for (metric, bench, variant), cols in groups.items():
            if metric not in settings.metrics:
                continue
            if comp.variant is not None:
                if variant != comp.variant or (metric, bench, comp.ref_variant) not in groups:
                    continue
                ref_group = groups[(metric, bench, comp.ref_variant)]
            else:
                ref_group = cols
            for at in _places(cols, settings):
                row_cols = select_columns(cols, at)
                by_n = {c.n_points: c for c in select_columns(ref_group, at)}
                ref_cols = [by_n.get(c.n_points) for c in row_cols]
                if not row_cols or any(c is None for c in ref_cols):
                    continue
                line = compare_columns(table, comp, metric, bench, variant, at,  # type: ignore[arg-type]
                                       ref_cols, row_cols, source, settings)
                if not keep_empty and line.paper_diff is None and (not line.ref_runs or not line.row_runs):
                    continue  # neither the paper nor we have both numbers: nothing to say
                lines.append(line)
    return lines
