"""The paper's findings, tested: ``reports/findings.{md,csv,tex}`` (``findings`` in conf/report.yaml).

A finding is a claim of the paper (PCR-CG > Predator on 3DLoMatch, explicit > implicit, ...) written
as named row selections (an experiment and ``where`` filters, the table rows' selection language;
they may come from different experiments) and comparisons ``[reference, compared]`` that the claim
says go the ``expect`` way. Each comparison is filled and tested exactly as a table's orderings
(:func:`pcrcg.report.tables.fill_table`, :func:`pcrcg.report.orderings.check_orderings`): ours as
the mean ± std over seeds of the difference, the paired bootstrap interval over the test pairs with
several seeds drawn seed against seed before the pairs (``stats.seeds``), at every place of ``stats.at``
(5000 points, the mean over N).

Verdict of a line: ``holds`` / ``reversed`` (the interval excludes 0 on the expected / the other
side), ``not resolved`` (it includes 0, or there is no interval: the note says why), ``not run``
(a row has no finished run: the note names the experiment, the row and the command that runs it).
A claim's verdict combines its lines (every comparison at every place): ``reversed`` if any is,
else ``not run`` if any is, else ``holds`` if all hold, else ``not resolved``.

The real scene (``findings.real``, e.g. ``real-redkitchen``): the same selections and runs, the
metrics ``<real>/<benchmark>/rr_<N>`` and per-pair artifacts ``<real>/pairs/<benchmark>.csv`` that
``python -m pcrcg.evaluate mode=tracked name=<real>`` logs on them; "—" where no run has them.

The profile's own targets (``findings.targets``, e.g. geometry-only Predator >= FPFH + RANSAC + 10 points
on generated 3DMatch) are tested the same way against a ``margin``: *met* when the interval clears the
margin on the expected side, *missed* when it lies wholly short of it, else *not resolved*. A row with
``n_points: null`` is its one estimate per pair (FPFH + RANSAC samples no N), compared with every sample
size of the other row. Targets have no real-scene column and no paper number.

``python -m pcrcg.report.findings --jobs`` prints the jobs that run every row (``sweeps/findings.sh``).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import pandas as pd

from pcrcg.errors import ConfigError
from pcrcg.report.orderings import (MEAN, OrderingLine, StatsSettings, check_orderings, compare_columns,
                                    select_columns)
from pcrcg.report.spec import Column, Comparison, Row, TableSpec, report_where, run_command, with_defaults
from pcrcg.report.stats import HOLDS, REVERSED, seed_rule_text
from pcrcg.report.tables import (FilledTable, _paper_value, counted_text, fill_table, machines_text, paper_values,
                                 run_code, run_counts, run_machine)
from pcrcg.tracking.git import DEFAULT_IDENTITY, same_code

NOT_RESOLVED = "not resolved"
NOT_RUN = "not run"
MET = "met"
MISSED = "missed"
EXPECT = {"higher": 1, "lower": -1}
DASH = "—"


@dataclass(frozen=True)
class Selection:
    """One named row of a finding: which runs, the job that makes them, the paper's entry."""

    name: str
    experiment: str
    where: Mapping[str, Any]
    job: str
    paper_table: str = ""
    method: str = ""
    variant: str = ""
    single: bool = False  # n_points: null: its one estimate per pair, against every sample size of the other row

    def row(self) -> Row:
        return Row(method=self.method, variant=self.variant, label=self.name, where=dict(self.where),
                   experiment=self.experiment)

    def command(self, profile: str | None, seeds: Sequence[int]) -> str:
        """The command that runs this row's configs (every seed of the findings)."""
        return run_command(self.experiment, self.job, profile, seeds) + ("" if seeds else " -m")


@dataclass(frozen=True)
class Finding:
    number: int
    claim: str
    benchmark: str
    metric: str
    n_points: tuple[int, ...] | None
    expect: str
    rows: tuple[Selection, ...]
    compare: tuple[tuple[str, str], ...]
    margin: float | None = None  # a target of the profile (findings.targets); None: a claim of the paper
    # what in this project's setting differs from the paper's for this claim (findings.claims[].differs): shown
    # under the findings where the claim is reversed or not resolved
    differs: str | None = None

    @property
    def sign(self) -> int:
        return EXPECT[self.expect]

    @property
    def is_target(self) -> bool:
        return self.margin is not None

    @property
    def label(self) -> str:
        """``3`` for a claim, ``T1`` for a target."""
        return f"T{self.number}" if self.is_target else str(self.number)

    @property
    def has_single(self) -> bool:
        """Whether a row is its one estimate per pair (``n_points: null``) beside rows of several sizes."""
        return bool(self.n_points) and any(s.single for s in self.rows)

    def verdict(self, line: OrderingLine) -> str:
        """A line's verdict: :func:`target_verdict` against the margin for a target, else :func:`line_verdict`."""
        return line_verdict(self.sign, line) if self.margin is None else target_verdict(self.sign, self.margin, line)

    def selection(self, name: str) -> Selection:
        return next(s for s in self.rows if s.name == name)


@dataclass(frozen=True)
class FindingsSpec:
    claims: tuple[Finding, ...]
    real: str | None = None
    real_root: str = "data/real-redkitchen"
    seeds: tuple[int, ...] = (0, 1, 2)
    targets: tuple[Finding, ...] = ()
    where: Mapping[str, Any] = field(default_factory=dict)  # the report-wide filters the rows inherit
    registration: str | None = None  # the group of conf/registration/ those filters select (registration_of)

    @property
    def all(self) -> tuple[Finding, ...]:
        """The claims, then the targets."""
        return self.claims + self.targets

    @property
    def experiments(self) -> list[str]:
        """Every experiment a row reads (claims and targets)."""
        return list(dict.fromkeys(s.experiment for f in self.all for s in f.rows))

    @property
    def real_experiments(self) -> list[str]:
        """The experiments evaluated on the real scene: the claims' rows', and those of targets on a benchmark of
        the real data set (``<real>/<benchmark>``)."""
        on_real = [f for f in self.targets if self.real and f.benchmark.startswith(f"{self.real}/")]
        return list(dict.fromkeys(s.experiment for f in self.claims + tuple(on_real) for s in f.rows))

    def jobs(self) -> list[tuple[str, str]]:
        """Unique ``(experiment, overrides)`` jobs that run every row, the claims' then the targets', in order."""
        return list(dict.fromkeys((s.experiment, s.job) for f in self.all for s in f.rows))

    def real_command(self) -> str:
        return (f"python -m pcrcg.evaluate mode=tracked experiments=[{','.join(self.real_experiments)}] "
                f"data.root={self.real_root} name={self.real}")


def _with_registration(job: str, registration: str) -> str:
    """``job`` (overrides) with ``registration=<registration>`` instead of its own registration overrides."""
    kept = [t for t in job.split() if not t.startswith(("registration=", "registration."))]
    return " ".join([*kept, f"registration={registration}"])


def _registration_dir(conf_dir: str | Path | None = None) -> Path:
    from pcrcg.config import CONF_DIR

    return Path(conf_dir or CONF_DIR) / "registration"


def _settings(path: Path) -> dict[str, str]:
    """A group file of conf/registration/ as flat ``{"registration.<key>": "<value>"}``, without its defaults list."""
    from omegaconf import OmegaConf

    from pcrcg.tracking.hashing import flatten

    node = OmegaConf.to_container(OmegaConf.load(path))
    if not isinstance(node, dict):
        raise ConfigError("registration", str(path), "a mapping of settings")
    node.pop("defaults", None)
    return {f"registration.{k}": v for k, v in flatten(node).items()}


def registration_where(registration: str, conf_dir: str | Path | None = None) -> dict[str, str]:
    """The filters that select the runs of ``registration``, a group of conf/registration/ that inherits
    ``default`` and sets only what differs: ``{"registration.<key>": "<value>"}`` per setting of its file,
    e.g. ``inlier_ranking`` -> ``{"registration.ransac.score": "correspondences"}``."""
    path = _registration_dir(conf_dir) / f"{registration}.yaml"
    if registration == "default" or not path.is_file():
        options = sorted(p.stem for p in path.parent.glob("*.yaml") if p.stem != "default")
        raise ConfigError("registration", registration, " | ".join(options))
    return _settings(path)


def registration_overrides(registration: str, conf_dir: str | Path | None = None) -> list[str]:
    """The overrides of ``python -m pcrcg.report`` that select the runs of ``registration`` (the report-wide
    ``where``): ``++where.registration.ransac.score='correspondences'`` for ``inlier_ranking``."""
    return [f"++where.{k}='{v}'" for k, v in registration_where(registration, conf_dir).items()]


def registration_of(defaults: Mapping[str, Any], conf_dir: str | Path | None = None) -> str | None:
    """The group of conf/registration/ whose runs the report-wide ``defaults`` select: its own settings are all
    among the ``registration.*`` filters, and every such filter has the group's value (``default.yaml``'s where
    the group sets none): ``inlier_ranking`` for ``registration.ransac.score=correspondences``. None when no group
    is (the paper's protocol, ``overlap``: the rows' own jobs)."""
    own = {k: str(v) for k, v in defaults.items() if k.startswith("registration.")}
    if not own:
        return None
    base = _settings(_registration_dir(conf_dir) / "default.yaml")
    for path in sorted(_registration_dir(conf_dir).glob("*.yaml")):
        if path.stem == "default":
            continue
        group = _settings(path)
        if all(own.get(k) == v for k, v in group.items()) and all({**base, **group}.get(k) == v for k, v in own.items()):
            return path.stem
    return None


def _selection(raw: Mapping[str, Any], where: str, target: bool = False,
               defaults: Mapping[str, Any] | None = None, registration: str | None = None) -> Selection:
    for key in ("name", "experiment", "where") + (() if target else ("paper",)):
        if not raw.get(key):
            kind = "target" if target else "finding"
            raise ConfigError(f"{where}.{key}", raw.get(key), f"set for every row of a {kind}")
    if "n_points" in raw and raw["n_points"] is not None:
        raise ConfigError(f"{where}.n_points", raw["n_points"],
                          "null (the row's one estimate per pair), or leave it out (the finding's sizes)")
    paper = raw.get("paper") or {}
    if not target and (not isinstance(paper, Mapping) or not paper.get("table") or not paper.get("method")):
        raise ConfigError(f"{where}.paper", paper, "{table, method[, variant]} of paper_tables.csv")
    if not isinstance(paper, Mapping):
        raise ConfigError(f"{where}.paper", paper, "{table, method[, variant]} of paper_tables.csv, or leave it out")
    job = str(raw.get("job") or "")
    if registration and not any(str(k).startswith("registration.") for k in raw["where"]):
        job = _with_registration(job, registration)  # the row's runs are those of the report-wide ranking
    return Selection(str(raw["name"]), str(raw["experiment"]), with_defaults(raw["where"], defaults or {}), job,
                     str(paper.get("table") or ""), str(paper.get("method") or ""), str(paper.get("variant") or ""),
                     single="n_points" in raw)


def _sizes(raw: Any, where: str) -> tuple[int, ...] | None:
    if raw is None:
        return None
    try:
        return tuple(int(n) for n in raw)
    except (TypeError, ValueError):
        raise ConfigError(where, raw, "a list of sample sizes, or null") from None


def _finding(c: Mapping[str, Any], k: int, raw: Mapping[str, Any], where: str, target: bool,
             defaults: Mapping[str, Any] | None = None, registration: str | None = None) -> Finding:
    """One claim (``findings.claims[k-1]``) or target (``findings.targets[k-1]``, with its ``margin``)."""
    rows = tuple(_selection(r, f"{where}.rows[{i}]", target, defaults, registration)
                 for i, r in enumerate(c.get("rows") or []))
    names = [r.name for r in rows]
    if len(set(names)) != len(names) or len(rows) < 2:
        raise ConfigError(f"{where}.rows", names, "at least two rows with different names")
    compare = []
    for item in c.get("compare") or []:
        if not isinstance(item, (list, tuple)) or len(item) != 2 or any(str(n) not in names for n in item):
            raise ConfigError(f"{where}.compare", item,
                              "a pair [reference, compared] of row names: " + ", ".join(names))
        if all(next(r for r in rows if r.name == str(n)).single for n in item):
            raise ConfigError(f"{where}.compare", item, "at most one side with n_points: null")
        compare.append((str(item[0]), str(item[1])))
    if not compare:
        raise ConfigError(f"{where}.compare", c.get("compare"), "at least one pair [reference, compared]")
    expect = str(c.get("expect", raw.get("expect", "higher")))
    if expect not in EXPECT:
        raise ConfigError(f"{where}.expect", expect, " | ".join(EXPECT))
    sizes = _sizes(c["n_points"] if "n_points" in c else raw.get("n_points"), f"{where}.n_points")
    if sizes is None and any(r.single for r in rows):
        raise ConfigError(f"{where}.n_points", None,
                          "sample sizes for the rows that have them (a row has n_points: null)")
    margin = None
    if target:
        margin = c.get("margin", 0.0)
        if isinstance(margin, bool) or not isinstance(margin, (int, float)) or margin < 0:
            raise ConfigError(f"{where}.margin", margin, "a non-negative number of points, e.g. 10")
        margin = float(margin)
    text = c.get("target" if target else "claim") or f"{'target' if target else 'finding'} {k}"
    differs = c.get("differs")
    if differs is not None and (not isinstance(differs, str) or not differs.strip()):
        raise ConfigError(f"{where}.differs", differs,
                          "a text (what in our setting differs from the paper's), or leave it out")
    return Finding(k, str(text), str(c.get("benchmark", raw.get("benchmark", "3DLoMatch"))),
                   str(c.get("metric", raw.get("metric", "RR"))), sizes, expect, rows, tuple(compare), margin,
                   " ".join(differs.split()) if differs else None)


def parse_findings(raw: Mapping[str, Any] | None, defaults: Mapping[str, Any] | None = None) -> FindingsSpec | None:
    """``findings`` node of conf/report.yaml -> :class:`FindingsSpec` (None: no findings). ``defaults``: the
    report's flat filters that every row inherits unless it sets the key (:func:`pcrcg.report.spec.report_where`).
    When they select the runs of a registration group (:func:`registration_of`, e.g. ``inlier_ranking``), a row
    that sets no ``registration.*`` filter of its own runs its job with that group (``registration=<group>``)."""
    if not raw:
        return None
    registration = registration_of(defaults) if defaults else None
    claims = tuple(_finding(c, k, raw, f"findings.claims[{k - 1}]", False, defaults, registration)
                   for k, c in enumerate(raw.get("claims") or [], 1))
    if not claims:
        raise ConfigError("findings.claims", raw.get("claims"), "a list of claims (or findings: null)")
    targets = tuple(_finding(c, k, raw, f"findings.targets[{k - 1}]", True, defaults, registration)
                    for k, c in enumerate(raw.get("targets") or [], 1))
    real = raw.get("real")
    seeds = tuple(int(s) for s in (raw.get("seeds") or ()))
    return FindingsSpec(claims, str(real) if real else None, str(raw.get("real_root") or "data/real-redkitchen"),
                        seeds, targets, dict(defaults or {}), registration)


# ---------------------------------------------------------------------------------------------- filling


@dataclass
class FindingLine:
    """One comparison of a finding at one place of ``stats.at``: ours on the generated data and the real scene."""

    finding: Finding
    reference: Selection
    compared: Selection
    ours: OrderingLine
    real: OrderingLine | None = None
    verdict: str = NOT_RESOLVED
    real_verdict: str | None = None
    note: str | None = None
    real_note: str | None = None

    @property
    def comparison(self) -> str:
        return f"{self.compared.name} − {self.reference.name}"

    @property
    def where(self) -> str:
        at = self.ours.at
        text = " ".join(p for p in (self.finding.benchmark, self.finding.metric,
                                    "" if at is None else ("mean over N" if at == MEAN else str(at))) if p)
        single = [s.name for s in (self.reference, self.compared) if s.single]
        return text + (f" ({single[0]}: its one estimate per pair)" if single else "")


@dataclass
class RowSeeds:
    """The seeds behind one job of the findings (rows that share it: main_results' PCR-CG is five rows)."""

    experiment: str
    job: str
    names: list[str]
    seeds: set[str] = field(default_factory=set)  # seeds of the runs the findings count
    seedless: bool = False  # its runs do not read the seed: one stands for every seed
    runs: dict[str, str] = field(default_factory=dict)  # run id -> seed, of the runs the findings count

    def missing(self, wanted: Sequence[int]) -> list[int]:
        return [] if self.seedless else [s for s in wanted if str(s) not in self.seeds]

    def seeds_text(self) -> str:
        if self.seedless:
            return "any (the run does not read its seed)"
        return ", ".join(sorted(self.seeds, key=lambda x: (len(x), x))) or DASH


# the validation curves a learned run logs (pcrcg.models.module): Predator's feature-match recall, the gate of its
# matchability loss (1 at a validation after which the loss is on), the overlap head's recall; the lifted features'
# share of the test points
VAL_RECALL, GATE, OVERLAP_RECALL, COVERAGE = "val/recall", "val/matchability_gate", "val/overlap_recall", "color_coverage"
THRESHOLD = "model.loss.matchability_after_recall"


@dataclass
class TrainingRow:
    """How one counted run of a findings job trained: its validation feature-match recall (last and best), the
    validations after which its matchability loss was on (``gate_on`` of ``gate_total``, the first at step
    ``first_on``; ``on_steps``) under the run's ``threshold`` (0: on from the first step), its recall ``curve``, the
    overlap head's last validation recall and the lifted features' share of the test points (None: not logged)."""

    names: list[str]
    experiment: str
    job: str
    seed: str
    run_id: str
    recall_last: float | None = None
    recall_best: float | None = None
    threshold: float | None = None
    gate_total: int = 0
    overlap_recall: float | None = None
    coverage: float | None = None
    curve: list[tuple[int, float]] = field(default_factory=list)  # (step, validation feature recall)
    on_steps: list[int] = field(default_factory=list)  # the validations after which the matchability loss was on
    matchability: bool = True  # False: a model without Predator's matchability loss (GeoTransformer, CoFiNet)

    @property
    def gate_on(self) -> int:
        return len(self.on_steps)

    @property
    def first_on(self) -> int | None:
        return self.on_steps[0] if self.on_steps else None

    def gate_text(self) -> str:
        if not self.matchability:
            return "none (the model has no matchability loss)"
        if self.threshold is not None and self.threshold <= 0:
            return "on from the first step"
        if self.gate_total == 0:
            return DASH
        if self.gate_on == 0:
            return f"never on (0 of {self.gate_total} validations)"
        return f"on from step {self.first_on} ({self.gate_on} of {self.gate_total} validations)"


def _number(row: pd.Series | None, key: str) -> float | None:
    v = None if row is None else row.get(key)
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return None if math.isnan(v) else v


def _earlier_parts(run: pd.Series, runs: pd.DataFrame) -> list[str]:
    """Run ids of the unfinished runs of the same experiment, config and code that started before ``run``, oldest
    first: a training resumed from ``last.ckpt`` is a new run, and the validations before the resumption are
    in the run that was stopped."""
    need = ("tags.config_hash", "tags.code_version", "experiment", "status", "start_time")
    if any(k not in runs.columns for k in need) or any(pd.isna(run.get(k)) for k in need[:3]):
        return []
    same = runs[(runs["experiment"] == run["experiment"]) & (runs["tags.config_hash"] == run["tags.config_hash"])
                & (runs["tags.code_version"] == run["tags.code_version"]) & (runs["status"] != "FINISHED")
                & (runs["start_time"] < run["start_time"])]
    return [str(r) for r in same.sort_values("start_time")["run_id"]]


def _threshold(row: pd.Series | None) -> float | None:
    """The run's validation recall above which its matchability loss was on (0: from the first step), its logged
    ``model.loss.matchability_after_recall`` resolved as the run resolved it (``official``: by whether it lifted 2D
    features, :meth:`pcrcg.models.losses.LossConfig.matchability_threshold`)."""
    from pcrcg.errors import ConfigError
    from pcrcg.models.losses import OFFICIAL, LossConfig

    setting = OFFICIAL if row is not None and row.get(f"params.{THRESHOLD}") == OFFICIAL else _number(
        row, f"params.{THRESHOLD}")
    if setting is None:
        return None
    lifted = str(row.get("params.features.name")) not in ("none", "None", "nan")
    try:
        return LossConfig(matchability_after_recall=setting).matchability_threshold(lifted)
    except ConfigError:  # a logged value no run accepts
        return None


def _curve(history: Any, run_ids: Sequence[str], key: str) -> list[tuple[int, float]]:
    """Metric ``key`` over the parts of one training (oldest first): at a step that several parts logged, the
    latest part's value (it went on from there)."""
    merged: dict[int, float] = {}
    for rid in run_ids:
        merged.update(dict(history(rid, key)) if history is not None else {})
    return sorted(merged.items())


def training_rows(row_seeds: Sequence[RowSeeds], runs: pd.DataFrame, source: Any) -> list[TrainingRow]:
    """A :class:`TrainingRow` per counted run that logged validation curves (learned models; classical methods
    have none), job by job in the findings' order, seeds ascending; the curves of a resumed training joined
    from its parts (:func:`_earlier_parts`). ``source``: anything with
    ``metric_history(run_id, key) -> [(step, value), ...]`` (:class:`pcrcg.report.outcomes.OutcomeSource`)."""
    history = getattr(source, "metric_history", None)
    by_id = getattr(source, "params", None) or ({str(r["run_id"]): r for _, r in runs.iterrows()} if len(runs) else {})
    out = []
    for rs in row_seeds:
        for run_id, seed in sorted(rs.runs.items(), key=lambda kv: (len(kv[1]), kv[1], kv[0])):
            row = by_id.get(run_id)
            if _number(row, f"metrics.{VAL_RECALL}") is None:
                continue
            tr = TrainingRow(list(rs.names), rs.experiment, rs.job, seed, run_id,
                             recall_last=_number(row, f"metrics.{VAL_RECALL}"),
                             threshold=_threshold(row),
                             overlap_recall=_number(row, f"metrics.{OVERLAP_RECALL}"),
                             coverage=_number(row, f"metrics.{COVERAGE}"))
            parts = [*_earlier_parts(row, runs), run_id]
            tr.curve = _curve(history, parts, VAL_RECALL)
            tr.recall_best = max((v for _, v in tr.curve), default=tr.recall_last)
            tr.matchability = str(row.get("params.model.name")) in ("predator", "None", "nan")
            if tr.matchability:
                gate = _curve(history, parts, GATE)
                tr.on_steps, tr.gate_total = [step for step, v in gate if v > 0], len(gate)
            else:
                tr.threshold = None
            out.append(tr)
    return out


TRAINING_INTRO = (
    "Each learned run behind the rows: its validation feature-match recall (the share of sampled validation "
    "correspondences whose nearest descriptor is a true match, Predator's training `recall`) at the last "
    "validation and the best one; the validations after which the matchability loss was on "
    "(`model.loss.matchability_after_recall`: `official`, as each official trainer, is Predator's schedule, on while "
    "that recall is above 0.3, geometry only and on from the first step with 2D features, as PCR-CG's; a number, "
    "that threshold); the overlap "
    "head's validation recall; and the share of the test points that the lifted 2D features reach. A run whose "
    "recall never passes the threshold trains without the matchability loss: its backbone never learns from that "
    "loss, and its matchability head gives every point the same score, so that its evaluation samples points by "
    "overlap alone (where a fragment has more points than N; with fewer, Predator's script draws N uniformly with "
    "replacement). A comparison with such a run compares training schedules as well as features.")


def training_markdown(filled: "FilledFindings", heading: str = "###") -> list[str]:
    """The section on how the rows' models trained (:func:`training_rows`); [] when no counted run logged curves."""
    if not filled.training:
        return []
    out = [f"{heading} How the rows' models trained", "", TRAINING_INTRO, "",
           "| Rows | Job | Seed | Val. feature recall, last (best) | Matchability loss | Val. overlap recall | "
           "Color coverage |", "|---|---|---:|---:|---|---:|---:|"]

    def pct(v: float | None) -> str:
        return DASH if v is None else f"{100 * v:.1f}%"

    for t in filled.training:
        out.append(f"| {', '.join(t.names)} | `{t.experiment}` {t.job} | {t.seed} | {pct(t.recall_last)} "
                   f"({pct(t.recall_best)}) | {t.gate_text()} | {pct(t.overlap_recall)} | {pct(t.coverage)} |")
    if any(t.curve for t in filled.training):
        out += ["", f"![Validation feature recall of each run over training, filled where the matchability loss was on]"
                    f"({TRAINING_FIGURE})"]
    return out + [""]


@dataclass
class FilledFindings:
    spec: FindingsSpec
    lines: list[FindingLine]
    profiles: Mapping[str, str | None]
    identity: str = DEFAULT_IDENTITY
    codes: dict[str, int] = field(default_factory=dict)
    row_seeds: list[RowSeeds] = field(default_factory=list)
    training: list[TrainingRow] = field(default_factory=list)
    machines: dict[str, int] = field(default_factory=dict)  # machine (run_machine) -> runs of it behind the findings

    def missing_runs(self) -> list[tuple[RowSeeds, list[int]]]:
        """Each job with seeds of ``spec.seeds`` that no counted run has, and those seeds."""
        return [(r, m) for r in self.row_seeds if (m := r.missing(self.spec.seeds))]

    def claim_verdict(self, finding: Finding, real: bool = False) -> str | None:
        """The claim's (or target's) verdict over its lines (module docstring); None when the real column is
        left out."""
        vs = [ln.real_verdict if real else ln.verdict for ln in self.lines if ln.finding is finding]
        if real and (self.spec.real is None or all(v is None for v in vs)):
            return None
        bad, good = (MISSED, MET) if finding.is_target else (REVERSED, HOLDS)
        if bad in vs:
            return bad
        if NOT_RUN in vs:
            return NOT_RUN
        if vs and all(v == good for v in vs):
            return good
        return NOT_RESOLVED if vs else None

    def identity_text(self) -> str:
        rule = ("same config and code (identity=config_and_code): each row counts the runs of one code version, "
                "its newest run's" if same_code(self.identity) else
                "same config (identity=config): a row's seeds may come from different code versions")
        where = ", ".join(f"{k}={v}" for k, v in self.spec.where.items())
        scope = (f"; a row counts only runs with {where} unless it sets the key itself (the report-wide `where`"
                 + (f": the runs of registration={self.spec.registration}" if self.spec.registration else "")
                 + ")") if where else ""
        return (f"Runs counted: {rule}{scope}; code versions behind the findings: {counted_text(self.codes)}."
                f"{machines_text(self.machines)}")


def line_verdict(sign: int, line: OrderingLine) -> str:
    """holds / reversed / not resolved / not run of one compared line (``sign``: the expected one)."""
    if not line.ref_runs or not line.row_runs:
        return NOT_RUN
    iv = line.interval
    if iv is None:
        return NOT_RESOLVED
    if iv.lo > 0:
        return HOLDS if sign > 0 else REVERSED
    if iv.hi < 0:
        return HOLDS if sign < 0 else REVERSED
    return NOT_RESOLVED


def target_verdict(sign: int, margin: float, line: OrderingLine) -> str:
    """met / missed / not resolved / not run of one line of a target: the difference should be at least
    ``margin`` points on the ``sign`` side (higher: ``lo >= margin`` is met, ``hi < margin`` missed). "At least":
    an interval that reaches the margin meets it (two rows registering the same pairs, ``[0, 0]``, meet a
    margin of 0; the claims' orderings stay strict)."""
    if not line.ref_runs or not line.row_runs:
        return NOT_RUN
    iv = line.interval
    if iv is None:
        return NOT_RESOLVED
    lo, hi = (iv.lo, iv.hi) if sign > 0 else (-iv.hi, -iv.lo)
    if lo >= margin:
        return MET
    if hi < margin:
        return MISSED
    return NOT_RESOLVED


def _table(finding: Finding, benchmark: str) -> TableSpec:
    rows = tuple(s.row() for s in finding.rows)
    by_name = {r.label: r for r in rows}
    sizes: tuple[int | None, ...] = finding.n_points or (None,)
    if finding.has_single:
        sizes += (None,)  # the column of the rows' one estimate per pair
    cols = tuple(Column(benchmark, finding.metric, n) for n in sizes)
    return TableSpec(name=f"finding {finding.label}", title=finding.claim, experiment=finding.rows[0].experiment,
                     rows=rows, columns=cols, paper_table="",
                     compare=tuple(Comparison(by_name[a], by_name[b]) for a, b in finding.compare))


def _single_orderings(finding: Finding, table: FilledTable, benchmark: str, source: Any,
                      settings: StatsSettings) -> list[OrderingLine]:
    """The lines of a finding with a row of one estimate per pair (``n_points: null``): at each place of
    ``stats.at``, that row's column against the other row's columns of the place (for the mean over N the
    same outcome at every size, so its mean is that outcome)."""
    sized = [c for c in table.spec.columns if c.n_points is not None]
    one = next(c for c in table.spec.columns if c.n_points is None)
    lines = []
    for comp in table.spec.compare:
        ref_single, row_single = (finding.selection(r.label).single for r in (comp.ref, comp.row))
        for at in settings.at:
            cols = select_columns(sized, at)
            if not cols:
                continue
            lines.append(compare_columns(table, comp, finding.metric, benchmark, "", at,
                                         [one] * len(cols) if ref_single else cols,
                                         [one] * len(cols) if row_single else cols, source, settings))
    return lines


def _fill(finding: Finding, benchmark: str, runs: pd.DataFrame, paper: pd.DataFrame | None,
          profiles: Mapping[str, str | None], identity: str, source: Any, settings: StatsSettings) -> FilledTable:
    table = fill_table(_table(finding, benchmark), runs, paper if paper is not None else pd.DataFrame(
        columns=["table", "method", "variant", "benchmark", "metric", "n_points", "value"]), profiles, identity)
    if paper is not None:  # each row's number from its own paper table
        paper_at = paper_values(paper)
        for cell in table.cells:
            sel = finding.selection(cell.row.label)
            cell.paper = _paper_value(paper_at, sel.paper_table, cell.row, cell.col) if sel.paper_table else None
    if finding.has_single:
        table.orderings = _single_orderings(finding, table, benchmark, source, settings)
    else:
        table.orderings = check_orderings(table, source, settings, keep_empty=True)
    return table


def _not_run_note(table: FilledTable, ref: Selection, row: Selection, profiles: Mapping[str, str | None],
                  seeds: Sequence[int]) -> str:
    """Each compared row without a finished run: why (the experiment and its filters, from the table
    machinery) and the command that runs it."""
    parts = []
    for sel in (ref, row):
        cells = [c for c in table.cells if c.row.label == sel.name]
        reason = next((c.reason or "no number of ours" for c in cells if c.mean is None), None)
        if reason is not None:
            parts.append(f"{sel.name}: {reason}; run it: `{sel.command(profiles.get(sel.experiment), seeds)}`")
    return "; ".join(parts) + " (or sweeps/findings.sh)" if parts else "no run of ours has both rows"


def fill_findings(spec: FindingsSpec, runs: pd.DataFrame, paper: pd.DataFrame, profiles: Mapping[str, str | None],
                  source: Any, settings: StatsSettings, identity: str = DEFAULT_IDENTITY) -> FilledFindings:
    """Every finding's lines from ``runs`` (the runs of ``spec.experiments``), see module docstring."""
    lines: list[FindingLine] = []
    used: set[str] = set()
    row_seeds: dict[tuple[str, str], RowSeeds] = {}
    for f in spec.all:
        ours = _fill(f, f.benchmark, runs, paper, profiles, identity, source, settings)
        for sel in f.rows:
            rs = row_seeds.setdefault((sel.experiment, sel.job), RowSeeds(sel.experiment, sel.job, []))
            if sel.name not in rs.names:
                rs.names.append(sel.name)
            refs = [r for c in ours.cells if c.row.label == sel.name for r in c.runs]
            rs.seeds |= {r.seed for r in refs}
            rs.runs.update({r.run_id: r.seed for r in refs})
            rs.seedless |= bool(refs) and all(r.seedless for r in refs)
        real = (_fill(f, f"{spec.real}/{f.benchmark}", runs, None, profiles, identity, source, settings)
                if spec.real and not f.is_target else None)
        used |= {r.run_id for c in ours.cells for r in c.runs}
        real_lines = real.orderings if real is not None else [None] * len(ours.orderings)
        for o, r in zip(ours.orderings, real_lines):
            ref, row = f.selection(o.comparison.ref.label), f.selection(o.comparison.row.label)
            fl = FindingLine(f, ref, row, o, r, verdict=f.verdict(o))
            if fl.verdict == NOT_RUN:
                fl.note = _not_run_note(ours, ref, row, profiles, spec.seeds)
            elif o.interval is None:
                fl.note = f"no interval: {o.reason}"
            if r is not None:
                fl.real_verdict = line_verdict(f.sign, r)
                if fl.verdict == NOT_RUN:
                    fl.real_verdict, fl.real_note = NOT_RUN, fl.note
                elif fl.real_verdict == NOT_RUN or r.interval is None:
                    if not r.ref_runs or not r.row_runs:
                        fl.real_verdict = None
                        fl.real_note = (f"not evaluated on {spec.real} (no run of a compared row has "
                                        f"{spec.real}/{f.benchmark}/ metrics); evaluate the runs: "
                                        f"`{spec.real_command()}`")
                    else:
                        fl.real_note = f"no interval on {spec.real}: {r.reason}"
            lines.append(fl)
    return FilledFindings(spec, lines, dict(profiles), identity, run_counts(run_code, runs, used),
                          list(row_seeds.values()), training_rows(list(row_seeds.values()), runs, source),
                          run_counts(run_machine, runs, used))


ABOVE, BELOW, WITHIN = "above", "below", "within"
PAPER_POSITION_TEXT = (
    "Paper Δ vs interval: where the paper's difference lies against our interval. *within*: our pairs and seeds "
    "cannot tell the paper's effect from ours (a *not resolved* line there needs more pairs or seeds); *above* / "
    "*below*: an effect of the paper's size is excluded here (a *not resolved* line with the paper's Δ *above* says "
    "that the effect the paper reports does not reproduce at its size in this setting, not that more pairs would "
    "find it).")


def paper_position(line: OrderingLine | None) -> str:
    """Where the paper's difference lies against our interval: ``within`` it (our pairs and seeds cannot tell the
    paper's effect from ours), ``above`` or ``below`` it (an effect of the paper's size is excluded here), or DASH
    (no interval, or no paper difference)."""
    p = None if line is None else line.paper_diff
    iv = None if line is None else line.interval
    if iv is None or p is None or (isinstance(p, float) and math.isnan(p)):
        return DASH
    return ABOVE if p > iv.hi else BELOW if p < iv.lo else WITHIN


# ---------------------------------------------------------------------------------------------- rendering


def _signed(v: float | None) -> str:
    return DASH if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:+.1f}"


def ours_text(line: OrderingLine | None) -> str:
    """Ours: the difference of our means, ± the std of the per-seed difference (two or more seeds on both rows)."""
    if line is None or not line.ref_runs or not line.row_runs or line.ours_diff is None:
        return DASH
    text = _signed(line.ours_diff)
    if line.n_seeds > 1 and line.ours_std is not None:
        text += f" ± {line.ours_std:.1f} ({line.n_seeds} seeds)"
    return text


def by_seed_text(line: OrderingLine | None) -> str:
    """``0:+1.2;1:-0.5``: the difference of each seed both rows ran (seed against seed), in seed order."""
    if line is None or not line.by_seed:
        return ""
    return ";".join(f"{k}:{_signed(v)}" for k, v in line.by_seed.items())


def _interval(line: OrderingLine | None) -> str:
    iv = None if line is None else line.interval
    return DASH if iv is None else f"[{_signed(iv.lo)}, {_signed(iv.hi)}]"


class _Notes:
    def __init__(self) -> None:
        self.items: list[str] = []

    def mark(self, note: str | None) -> str:
        if not note:
            return ""
        if note not in self.items:
            self.items.append(note)
        return f" [{self.items.index(note) + 1}]"


def _line_texts(fl: FindingLine, real: bool, notes: _Notes, first: bool) -> list[str]:
    f = fl.finding
    claim = f"{f.label}. {f.claim}" if first else ""
    # a target's column is what it asks for (≥ +10.0), a claim's the paper's difference
    wanted = (_signed(fl.ours.paper_diff) if f.margin is None
              else f"{'≥' if f.sign > 0 else '≤'} {_signed(f.sign * f.margin)}")
    out = [claim, fl.comparison, fl.where, wanted, ours_text(fl.ours), _interval(fl.ours)]
    if f.margin is None:  # a claim: where the paper's difference lies against our interval
        out.append(paper_position(fl.ours))
    out.append(fl.verdict + notes.mark(fl.note))
    if real:
        out += [ours_text(fl.real), _interval(fl.real), (fl.real_verdict or DASH) + notes.mark(fl.real_note)]
    return out


def _split(filled: FilledFindings) -> tuple[list[FindingLine], list[FindingLine]]:
    """The claims' lines and the targets' lines."""
    return ([ln for ln in filled.lines if not ln.finding.is_target],
            [ln for ln in filled.lines if ln.finding.is_target])


def _rows(lines: Sequence[FindingLine], real: bool, notes: _Notes) -> list[list[str]]:
    """Each line's cells (:func:`_line_texts`), the claim or target named on its first line only."""
    seen: set[int] = set()
    rows = []
    for fl in lines:
        rows.append(_line_texts(fl, real, notes, fl.finding.number not in seen))
        seen.add(fl.finding.number)
    return rows


def seeds_markdown(filled: FilledFindings, heading: str = "###") -> list[str]:
    """The seeds behind each job of the findings and the command that runs the missing ones (the sweep's progress)."""
    if not filled.row_seeds:
        return []
    wanted = ", ".join(str(s) for s in filled.spec.seeds) or DASH
    out = [f"{heading} Seeds behind the rows", "",
           f"Seeds the findings ask for: {wanted} (`findings.seeds`). A job that is several rows is run once.", "",
           "| Rows | Job | Seeds run | Missing | Command for the missing seeds |", "|---|---|---|---|---|"]
    for r in filled.row_seeds:
        missing = r.missing(filled.spec.seeds)
        cmd = f"`{run_command(r.experiment, r.job, filled.profiles.get(r.experiment), missing)}`" if missing else DASH
        out.append(f"| {', '.join(r.names)} | `{r.experiment}` {r.job} | {r.seeds_text()} | "
                   f"{', '.join(str(s) for s in missing) or DASH} | {cmd} |")
    return out + [""]


TARGETS_INTRO = ("The profile's own targets (`findings.targets`), tested as the claims: Δ = compared − reference, "
                 "the same intervals; *met* when the interval lies wholly at or beyond the target on its side, "
                 "*missed* when it lies wholly short of it, else *not resolved*.")


def intro(filled: FilledFindings) -> str:
    iv = next((ln.ours.interval for ln in filled.lines if ln.ours.interval is not None), None)
    how = (f"paired bootstrap {iv.level:.0%} interval over the test pairs ({iv.n_boot} resamples within each "
           f"scene, seed {iv.seed}; {seed_rule_text([ln.ours.interval for ln in filled.lines])}, as the tables' "
           "orderings)" if iv is not None else
           "paired bootstrap interval over the test pairs, as the tables' orderings")
    real = (f" The {filled.spec.real} columns: the same runs evaluated on the real scene "
            f"(`{filled.spec.real_command()}`); few pairs, wide intervals." if filled.spec.real else "")
    reg = filled.spec.registration
    ranked = (f"Every row that sets no registration filter of its own counts the runs registered with "
              f"`registration={reg}`, not the paper's protocol (the report-wide `where`). " if reg else "")
    return (ranked + "Δ = compared − reference, in points. Paper Δ: from the paper's tables (paper_tables.csv). Ours: the "
            "difference of our means over seeds, ± the std of the per-seed difference where both rows ran two or "
            f"more seeds. Interval: {how}. Verdict: *holds* (the interval excludes 0 on the claim's side), "
            "*reversed* (on the other side), *not resolved* (it includes 0, or no interval: see the note), "
            "*not run* (a row has no finished run: the note says which and the command). A claim's verdict: "
            "reversed if any of its lines is, else not run if any is, else holds if all hold, else not resolved. "
            + PAPER_POSITION_TEXT + real)


def differs_markdown(filled: FilledFindings, heading: str = "###") -> list[str]:
    """The section on what in our setting differs from the paper's: a paragraph per claim that is reversed or not
    resolved (ours or on the real scene) and has a ``differs`` text; [] when there is none."""
    items = []
    for f in filled.spec.claims:
        verdicts = [v for v in (filled.claim_verdict(f), filled.claim_verdict(f, real=True)) if v is not None]
        if f.differs and any(v in (REVERSED, NOT_RESOLVED) for v in verdicts):
            items.append(f"* **{f.number}. {f.claim}** ({' / '.join(verdicts)}): {f.differs}")
    if not items:
        return []
    return [f"{heading} Where our setting differs from the paper's", "",
            "For each claim that is reversed or not resolved here (ours / the real scene): what differs between the "
            "runs behind it and the paper's (`findings.claims[].differs` of conf/report.yaml), and what a run "
            "closer to the paper's would be expected to change.", "", *items, ""]


def to_markdown(filled: FilledFindings, heading: str = "##", figure: str | None = None) -> str:
    """The findings' section; ``figure``: the forest plot's file name, shown under the claims' table."""
    real = filled.spec.real is not None
    notes = _Notes()
    profiles = sorted({str(p) for e in filled.spec.experiments if (p := filled.profiles.get(e))})
    out = [f"{heading} The paper's findings, tested", "",
           f"Profile of our runs: `{', '.join(profiles) or 'any'}`. {intro(filled)}", ""]
    head = "| # | Claim | Verdict |" + (f" {filled.spec.real} |" if real else "")
    out += [head, "|---:|---|---|" + ("---|" if real else "")]
    for f in filled.spec.claims:
        cells = [str(f.number), f.claim, filled.claim_verdict(f) or DASH]
        if real:
            cells.append(filled.claim_verdict(f, real=True) or DASH)
        out.append("| " + " | ".join(cells) + " |")
    out += ["", "| Claim | Comparison | Where | Paper Δ | Ours Δ | 95% interval | Paper Δ vs interval | Verdict |"
            + (f" {filled.spec.real} Δ | {filled.spec.real} interval | {filled.spec.real} verdict |" if real else ""),
            "|---|---|---|---:|---:|---:|---|---|" + ("---:|---:|---|" if real else "")]
    claims, targets = _split(filled)
    out += ["| " + " | ".join(cells) + " |" for cells in _rows(claims, real, notes)] + [""]
    if figure:
        out += [f"![The findings: our differences with their intervals and seeds, the paper's]({figure})", ""]
    out += differs_markdown(filled, heading + "#")
    out += training_markdown(filled, heading + "#")
    if targets:
        out += [f"{heading}# Targets of the profile", "", TARGETS_INTRO, "",
                "| Target | Comparison | Where | Target Δ | Ours Δ | 95% interval | Verdict |",
                "|---|---|---|---:|---:|---:|---|"]
        out += ["| " + " | ".join(cells) + " |" for cells in _rows(targets, False, notes)] + [""]
    out += seeds_markdown(filled, heading + "#")
    if notes.items:
        out += ["Notes:", ""] + [f"{i}. {n}" for i, n in enumerate(notes.items, 1)] + [""]
    out += [filled.identity_text(), ""]
    return "\n".join(out)


def to_latex(filled: FilledFindings) -> str:
    from pcrcg.report.render import latex_escape

    real = filled.spec.real is not None
    notes = _Notes()
    header = ["Claim", "Comparison", "Where", r"Paper $\Delta$", r"Ours $\Delta$", "Interval",
              r"Paper $\Delta$ vs interval", "Verdict"]
    if real:
        header += [latex_escape(f"{filled.spec.real} {t}") for t in ("Δ", "interval", "verdict")]
    out = ["% generated by python -m pcrcg.report", r"\begin{table}[h]", r"\centering",
           f"\\caption{{The paper's findings, tested. {latex_escape(intro(filled).replace('*', '').replace('`', ''))}}}",
           r"\begin{tabular}{lll" + "r" * 3 + "ll" + ("rrl" if real else "") + "}", r"\toprule",
           " & ".join(header) + r" \\", r"\midrule"]
    claims, targets = _split(filled)
    out += [" & ".join(latex_escape(t) for t in cells) + r" \\" for cells in _rows(claims, real, notes)]
    out += [r"\bottomrule", r"\end{tabular}"]
    if targets:
        out += [r"\par\medskip", latex_escape(TARGETS_INTRO.replace("*", "").replace("`", "")) + r"\par",
                r"\begin{tabular}{lllrrrl}", r"\toprule",
                " & ".join(["Target", "Comparison", "Where", r"Target $\Delta$", r"Ours $\Delta$", "Interval",
                            "Verdict"]) + r" \\", r"\midrule"]
        out += [" & ".join(latex_escape(t) for t in cells) + r" \\" for cells in _rows(targets, False, notes)]
        out += [r"\bottomrule", r"\end{tabular}"]
    out.append(r"\end{table}")
    out += ["% notes:"] + [f"% [{i}] {n}" for i, n in enumerate(notes.items, 1)]
    out.append(f"% {filled.identity_text()}")
    return "\n".join(out) + "\n"


CSV_FIELDS = ("finding", "claim", "claim_verdict", "comparison", "reference", "compared", "reference_experiment",
              "compared_experiment", "benchmark", "metric", "at", "expect", "paper_diff", "ours_diff", "ours_std",
              "n_seeds", "ci_low", "ci_high", "ci_seeds", "paper_diff_vs_interval", "verdict", "note", "real", "real_ours_diff", "real_ours_std",
              "real_n_seeds", "real_ci_low", "real_ci_high", "real_verdict", "real_claim_verdict", "real_note",
              "reference_run_ids", "compared_run_ids", "code_versions", "margin", "ours_by_seed")


def _r(v: float | None) -> Any:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else round(float(v), 4)


def csv_rows(filled: FilledFindings) -> Iterable[dict]:
    codes = ";".join(filled.codes)
    for fl in filled.lines:
        o, r = fl.ours, fl.real
        yield {
            "finding": fl.finding.label, "claim": fl.finding.claim, "claim_verdict": filled.claim_verdict(fl.finding),
            "comparison": fl.comparison, "reference": fl.reference.name, "compared": fl.compared.name,
            "reference_experiment": fl.reference.experiment, "compared_experiment": fl.compared.experiment,
            "benchmark": fl.finding.benchmark, "metric": fl.finding.metric, "at": "" if o.at is None else o.at,
            "expect": fl.finding.expect, "paper_diff": _r(o.paper_diff),
            "ours_diff": _r(o.ours_diff) if o.ref_runs and o.row_runs else "",
            "ours_std": _r(o.ours_std) if o.n_seeds > 1 else "", "n_seeds": o.n_seeds,
            "ci_low": _r(o.interval.lo) if o.interval else "", "ci_high": _r(o.interval.hi) if o.interval else "",
            "ci_seeds": o.interval.seeds_label if o.interval else "",
            "paper_diff_vs_interval": "" if fl.finding.is_target or paper_position(o) == DASH else paper_position(o),
            "verdict": fl.verdict, "note": fl.note or "", "real": "" if fl.finding.is_target else filled.spec.real or "",
            "real_ours_diff": _r(r.ours_diff) if r is not None and r.ref_runs and r.row_runs else "",
            "real_ours_std": _r(r.ours_std) if r is not None and r.n_seeds > 1 else "",
            "real_n_seeds": r.n_seeds if r is not None else "",
            "real_ci_low": _r(r.interval.lo) if r is not None and r.interval else "",
            "real_ci_high": _r(r.interval.hi) if r is not None and r.interval else "",
            "real_verdict": fl.real_verdict or "", "real_claim_verdict": filled.claim_verdict(fl.finding, True) or "",
            "real_note": fl.real_note or "", "reference_run_ids": ";".join(o.ref_runs),
            "compared_run_ids": ";".join(o.row_runs), "code_versions": codes,
            "margin": "" if fl.finding.margin is None else _r(fl.finding.margin),
            "ours_by_seed": by_seed_text(o),
        }


FIGURE = "findings.png"
TRAINING_FIGURE = "findings_training.png"


def write_findings(filled: FilledFindings, out_dir: Path) -> list[Path]:
    """``findings.md``, ``findings.tex``, ``findings.csv``, the forest plot ``findings.png`` and, where a counted run
    logged validation curves, ``findings_training.csv`` (:func:`training_rows`) in ``out_dir``; returns them."""
    from pcrcg.plots.findings import plot_findings

    md, tex, path = out_dir / "findings.md", out_dir / "findings.tex", out_dir / "findings.csv"
    fig = plot_findings(filled, out_dir / FIGURE)
    md.write_text(to_markdown(filled, figure=FIGURE if fig is not None else None))
    tex.write_text(to_latex(filled))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        w.writeheader()
        w.writerows(csv_rows(filled))
    files = [md, tex, path] + ([fig] if fig is not None else [])
    if filled.training:  # how the rows' models trained, one line per run, and their validation curves
        files.append(out_dir / "findings_training.csv")
        cols = ("experiment", "job", "seed", "run_id", "recall_last", "recall_best", "threshold", "gate_on",
                "gate_total", "first_on", "overlap_recall", "coverage", "matchability")
        pd.DataFrame([{**{k: getattr(t, k) for k in cols}, "rows": "; ".join(t.names),
                       "matchability_loss": t.gate_text()}
                      for t in filled.training]).to_csv(files[-1], index=False)
        from pcrcg.plots.findings import plot_training

        curves = plot_training(filled.training, out_dir / TRAINING_FIGURE)
        files += [curves] if curves is not None else []
    return files


# ---------------------------------------------------------------------------------------------- jobs (sweeps/findings.sh)


def load_findings(path: str | Path | None = None, where: Mapping[str, Any] | None = None) -> FindingsSpec | None:
    """The ``findings`` of conf/report.yaml (or of the report config at ``path``), with its ``where`` (flat
    filters in ``where`` replace or add to it: :func:`registration_where`)."""
    from omegaconf import OmegaConf

    from pcrcg.config import CONF_DIR

    cfg = OmegaConf.load(path or CONF_DIR / "report.yaml")
    node = cfg.get("findings")
    return parse_findings(OmegaConf.to_container(node, resolve=True) if node is not None else None,  # type: ignore[arg-type]
                          {**report_where(cfg), **(where or {})})


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m pcrcg.report.findings --jobs | --experiments | --real-experiments | --seeds | --report-overrides
    [--registration NAME]``: what sweeps/findings.sh runs."""
    p = argparse.ArgumentParser(prog="python -m pcrcg.report.findings", description=main.__doc__)
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--jobs", action="store_true", help="one job a line: <experiment> [overrides...]")
    what.add_argument("--experiments", action="store_true", help="the experiments, comma-separated")
    what.add_argument("--real-experiments", action="store_true",
                      help="the experiments evaluated on the real scene (the claims'), comma-separated")
    what.add_argument("--seeds", action="store_true", help="the seeds, comma-separated")
    what.add_argument("--report-overrides", action="store_true",
                      help="the overrides of `python -m pcrcg.report` that select the runs of --registration, one a line")
    p.add_argument("--registration", default=None,
                   help="a group of conf/registration/ (e.g. inlier_ranking): the findings of the runs so registered "
                        "(every row that sets no registration filter of its own runs its job with it)")
    p.add_argument("--config", default=None, help="a report config (default: conf/report.yaml)")
    args = p.parse_args(argv)
    try:  # a registration group that is not one: one line, before anything is printed
        where = registration_where(args.registration) if args.registration else {}
    except ConfigError as e:
        print(f"python -m pcrcg.report.findings: {e}", file=sys.stderr)
        return 2
    if args.report_overrides:
        print("\n".join(registration_overrides(args.registration) if args.registration else []))
        return 0
    spec = load_findings(args.config, where)
    if spec is None:
        return 0
    if args.jobs:
        for exp, job in spec.jobs():
            print(f"{exp} {job}".strip())
    elif args.experiments:
        print(",".join(spec.experiments))
    elif args.real_experiments:
        print(",".join(spec.real_experiments))
    else:
        print(",".join(str(s) for s in spec.seeds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
