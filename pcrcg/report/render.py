"""Write a filled table as Markdown, LaTeX and CSV, in the paper's layout.

Each row of the paper becomes up to three lines: the paper's numbers, ours (mean ± std
over seeds) and the difference (ours − paper). A missing number of ours is a dash with a
numbered note giving the reason; the runs behind every cell are listed under the table
(run id, config hash, git sha, profile, seed) and in the CSV, one line per cell.

Under a table that compares rows (``compare`` in conf/report.yaml), the paper's orderings
tested: the paper's difference, ours with its paired bootstrap interval over the test pairs
and the verdict (``pcrcg.report.orderings``); also ``<table>_orderings.csv``.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Iterable

from pcrcg.report.spec import LOWER_IS_BETTER, Column
from pcrcg.report.stats import seed_rule_text
from pcrcg.report.tables import Cell, FilledTable

DASH = "—"


def _digits(metric: str) -> int:
    return 3 if metric in LOWER_IS_BETTER else 1


def fmt_value(v: float | None, metric: str) -> str:
    if v is None or math.isnan(v):
        return DASH
    return f"{v:.{_digits(metric)}f}"


def fmt_ours(cell: Cell) -> str:
    if cell.mean is None:
        return DASH
    d = _digits(cell.col.metric)
    if len(cell.values) > 1:
        return f"{cell.mean:.{d}f} ± {cell.std:.{d}f}"
    return f"{cell.mean:.{d}f}"


def fmt_diff(cell: Cell) -> str:
    if cell.diff is None:
        return DASH
    return f"{cell.diff:+.{_digits(cell.col.metric)}f}"


def _mixed_metrics(cols: list[Column]) -> bool:
    return len({c.metric for c in cols}) > 1


def _col_header(col: Column, with_metric: bool = False) -> str:
    metric = col.section if with_metric else ""
    parts = [p for p in (col.label or col.variant, col.benchmark, metric, str(col.n_points) if col.n_points else "") if p]
    return " ".join(parts)


def _sections(table: FilledTable) -> list[tuple[str, list[Column]]]:
    """Sections stacked vertically, as in the paper's Table 1: one per metric when every metric
    has the same columns (benchmark x sample size); otherwise one section holding all columns."""
    groups: dict[str, list[Column]] = {}
    for col in table.spec.columns:
        groups.setdefault(col.metric, []).append(col)
    sigs = {tuple((c.benchmark, c.n_points, c.variant, c.label) for c in cols) for cols in groups.values()}
    metric_major = [c for cols in groups.values() for c in cols] == list(table.spec.columns)
    if len(groups) > 1 and len(sigs) == 1 and metric_major:
        return [(cols[0].section, cols) for cols in groups.values()]
    cols = list(table.spec.columns)
    return [("" if _mixed_metrics(cols) else cols[0].section, cols)]


class _Notes:
    """Numbered reasons for missing cells, shared by a table."""

    def __init__(self) -> None:
        self.items: list[str] = []

    def mark(self, reason: str | None) -> str:
        if not reason:
            return ""
        if reason not in self.items:
            self.items.append(reason)
        return f" [{self.items.index(reason) + 1}]"


def _lines(table: FilledTable, cols: list[Column], notes: _Notes, ours_mark: bool = True):
    """(label, [cell texts]) lines of a section: paper / ours / difference per spec row."""
    for row in table.spec.rows:
        cells = [table.cell(row, c) for c in cols]
        has_paper = any(c.paper is not None for c in cells)
        has_ours = any(c.mean is not None for c in cells)
        if row.reason and not row.where and has_paper:  # the paper's own baseline: no line of ours
            yield f"{row.text} (paper){notes.mark(row.reason)}", [fmt_value(c.paper, c.col.metric) for c in cells]
            continue
        if has_paper:
            yield f"{row.text} (paper)", [fmt_value(c.paper, c.col.metric) for c in cells]
        yield f"{row.text} (ours)", [fmt_ours(c) + (notes.mark(c.reason) if ours_mark and c.mean is None else "")
                                     for c in cells]
        if has_paper and has_ours:
            yield f"{row.text} (Δ ours − paper)", [fmt_diff(c) for c in cells]


def _trace(table: FilledTable) -> list[tuple[str, str, str]]:
    """(row, columns, runs) lines: which runs fill which cells."""
    out = []
    for row in table.spec.rows:
        groups: dict[tuple[str, ...], list[str]] = {}
        for c in table.cells:
            if c.row is row and c.runs:
                key = tuple(r.short() for r in c.runs)
                groups.setdefault(key, []).append(_col_header(c.col))
        for refs, cols in groups.items():
            span = cols[0] if len(cols) == 1 else f"{cols[0]} … {cols[-1]} ({len(cols)} cells)"
            out.append((row.text, span, "; ".join(refs)))
    return out


def fmt_signed(v: float | None, digits: int = 1) -> str:
    if v is None or math.isnan(v):
        return DASH
    return f"{v:+.{digits}f}"


def fmt_interval(iv) -> str:
    return DASH if iv is None else f"[{fmt_signed(iv.lo)}, {fmt_signed(iv.hi)}]"


def _ordering_texts(line, notes: _Notes) -> list[str]:
    """Comparison, where, paper Δ, ours Δ, interval, verdict of one ordering line."""
    ours = fmt_signed(line.ours_diff)
    if line.ours_diff is not None and line.n_seeds > 1:
        ours += f" ± {line.ours_std:.1f} ({line.n_seeds} seeds)"
    mark = line.verdict or DASH
    if line.interval is None and line.reason:
        mark += notes.mark(line.reason)
    return [line.comparison.text, line.where, fmt_signed(line.paper_diff), ours, fmt_interval(line.interval), mark]


def orderings_intro(table: FilledTable) -> str:
    iv = next((ln.interval for ln in table.orderings if ln.interval is not None), None)
    how = (f"paired bootstrap {iv.level:.0%} interval over the test pairs ({iv.n_boot} resamples of the pairs "
           f"within each scene, seed {iv.seed}; {seed_rule_text([ln.interval for ln in table.orderings])})"
           if iv is not None else "paired bootstrap interval over the test pairs")
    return ("Δ = row − reference, in points; ours: the difference of our means over seeds (± std of the per-seed "
            f"difference where both rows ran the same seeds); interval: {how}. Verdict: the paper's ordering "
            "*holds* (interval beyond 0 on the paper's side), is *reversed* (beyond 0 on the other side), or "
            "lies *within noise*.")


def to_markdown(table: FilledTable) -> str:
    spec = table.spec
    notes = _Notes()
    out = [f"## {spec.title}", ""]
    if spec.note:
        out += [spec.note, ""]
    out.append(f"Profile of our runs: `{table.profile or 'any'}`. Ours: mean ± std over seeds; "
               f"Δ = ours − paper.")
    out.append("")
    for section, cols in _sections(table):
        if section:
            out.append(f"**{section}**")
            out.append("")
        mixed = _mixed_metrics(cols)
        out.append("| | " + " | ".join(_col_header(c, mixed) for c in cols) + " |")
        out.append("|---|" + "---:|" * len(cols))
        for label, texts in _lines(table, cols, notes):
            out.append(f"| {label} | " + " | ".join(texts) + " |")
        out.append("")
    if table.orderings:
        out += ["**The paper's orderings, tested**", "", orderings_intro(table), "",
                "| Comparison | Where | Paper Δ | Ours Δ | 95% interval | Verdict |",
                "|---|---|---:|---:|---:|---|"]
        out += ["| " + " | ".join(_ordering_texts(line, notes)) + " |" for line in table.orderings]
        out.append("")
    if notes.items:
        out.append("Notes (why a number is missing):")
        out.append("")
        out += [f"{i}. {r}" for i, r in enumerate(notes.items, 1)]
        out.append("")
    if table.protocol:
        out.append("Protocol of these runs: " + "; ".join(table.protocol))
        out.append("")
    out += [table.identity_text(), ""]
    if table.shared:
        out += ["Rows that count another experiment's runs of their config: " + "; ".join(table.shared) + ".", ""]
    if table.fidelity:
        out.append("Settings of these runs that differ from the paper's text or its official code: "
                   + "; ".join(table.fidelity) + ".")
        out.append("")
    if table.coverage:
        out.append("Color coverage (fraction of points that received a 2D feature, ours): "
                   + ", ".join(f"{k}: {m:.3f}" + (f" ± {s:.3f}" if n > 1 else "")
                               for k, (m, s, n) in table.coverage.items()))
        out.append("")
    trace = _trace(table)
    if trace:
        out += ["Runs behind the cells:", "", "| Row | Cells | Runs |", "|---|---|---|"]
        out += [f"| {r} | {c} | {runs} |" for r, c, runs in trace]
        out.append("")
    return "\n".join(out)


_LATEX_ESC = {"&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_", "{": r"\{", "}": r"\}",
              "~": r"\textasciitilde{}", "^": r"\textasciicircum{}", "\\": r"\textbackslash{}"}


def latex_escape(text: str) -> str:
    s = "".join(_LATEX_ESC.get(ch, ch) for ch in text)
    return (s.replace("±", r"$\pm$").replace("Δ", r"$\Delta$").replace("−", "$-$").replace("≥", r"$\geq$")
            .replace("≤", r"$\leq$").replace(DASH, "--"))


def _header_levels(cols: list[Column]) -> list[tuple[str, list[str]]]:
    """(first cell, per-column texts) of each header line, from the outermost level in."""
    levels: list[tuple[str, list[str]]] = []
    if any(c.label or c.variant for c in cols):
        levels.append(("", [c.label or c.variant for c in cols]))
    levels.append(("", [c.benchmark for c in cols]))
    if _mixed_metrics(cols):
        levels.append(("", [c.section for c in cols]))
    if any(c.n_points for c in cols):
        levels.append((r"\# Sampled Points", [str(c.n_points or "") for c in cols]))
    return levels


def _latex_header(cols: list[Column]) -> list[str]:
    levels = _header_levels(cols)
    lines = []
    for depth, (first, texts) in enumerate(levels):
        keys = [tuple(lv[1][i] for lv in levels[: depth + 1]) for i in range(len(cols))]
        cells, i = [], 0
        while i < len(cols):
            j = i
            while j + 1 < len(cols) and keys[j + 1] == keys[i] and depth < len(levels) - 1:
                j += 1
            text = latex_escape(texts[i])
            if depth == 0 and len(levels) > 1:
                text = f"\\textbf{{{text}}}" if text else ""
            cells.append(f"\\multicolumn{{{j - i + 1}}}{{c}}{{{text}}}" if j > i else text)
            i = j + 1
        lines.append(f"{first} & " + " & ".join(cells) + r" \\")
    return lines


def to_latex(table: FilledTable) -> str:
    spec = table.spec
    sections = _sections(table)
    ncols = len(sections[0][1])
    notes = _Notes()
    out = ["% generated by python -m pcrcg.report; ours: mean $\\pm$ std over seeds",
           r"\begin{table}[h]", r"\centering", f"\\caption{{{latex_escape(spec.title)}}}",
           r"\begin{tabular}{l|" + "c" * ncols + "}", r"\toprule"]
    out += _latex_header(sections[0][1])
    out.append(r"\midrule")
    for section, cols in sections:
        if len(sections) > 1 or (section and cols[0].n_points is not None):
            out.append(f"& \\multicolumn{{{ncols}}}{{c}}{{\\textit{{{latex_escape(section)}}}}} \\\\")
            out.append(r"\midrule")
        for label, texts in _lines(table, cols, notes):
            out.append(latex_escape(label) + " & " + " & ".join(latex_escape(t) for t in texts) + r" \\")
        out.append(r"\midrule")
    out[-1] = r"\bottomrule"
    out += [r"\end{tabular}", r"\end{table}"]
    if table.orderings:
        intro = latex_escape(orderings_intro(table).replace("*", ""))
        out += ["", r"\begin{table}[h]", r"\centering",
                f"\\caption{{{latex_escape(spec.title)}: the paper's orderings, tested. {intro}}}",
                r"\begin{tabular}{llrrrl}", r"\toprule",
                r"Comparison & Where & Paper $\Delta$ & Ours $\Delta$ & Interval & Verdict \\", r"\midrule"]
        out += [" & ".join(latex_escape(t) for t in _ordering_texts(line, notes)) + r" \\" for line in table.orderings]
        out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    if notes.items:
        out += ["% missing numbers:"] + [f"% [{i}] {r}" for i, r in enumerate(notes.items, 1)]
    return "\n".join(out) + "\n"


CSV_FIELDS = ("table", "section", "row", "method", "variant", "benchmark", "metric", "n_points", "paper",
              "ours_mean", "ours_std", "n_runs", "diff", "status", "reason", "metric_key", "run_ids",
              "config_hashes", "git_shas", "profiles", "seeds")


def csv_rows(table: FilledTable) -> Iterable[dict]:
    for c in table.cells:
        yield {
            "table": table.spec.name,
            "section": c.col.section,
            "row": c.row.text,
            "method": c.row.method,
            "variant": c.col.variant or c.row.variant,
            "benchmark": c.col.benchmark,
            "metric": c.col.metric,
            "n_points": c.col.n_points if c.col.n_points is not None else "",
            "paper": "" if c.paper is None else c.paper,
            "ours_mean": "" if c.mean is None else round(c.mean, 4),
            "ours_std": "" if c.mean is None else round(c.std or 0.0, 4),
            "n_runs": len(c.values),
            "diff": "" if c.diff is None else round(c.diff, 4),
            "status": c.status,
            "reason": c.reason or "",
            "metric_key": c.metric_key or "",
            "run_ids": ";".join(r.run_id for r in c.runs),
            "config_hashes": ";".join(r.config_hash for r in c.runs),
            "git_shas": ";".join(r.git_sha for r in c.runs),
            "profiles": ";".join(r.profile for r in c.runs),
            "seeds": ";".join(r.seed for r in c.runs),
        }


def write_csv(table: FilledTable, path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        w.writerows(csv_rows(table))


ORDERING_FIELDS = ("table", "comparison", "reference", "row", "reference_variant", "variant", "metric", "benchmark",
                   "column_variant", "at", "paper_reference", "paper_row", "paper_diff", "ours_reference", "ours_row",
                   "ours_diff", "ours_diff_std", "n_seeds", "ci_low", "ci_high", "level", "n_boot", "boot_seed",
                   "ci_seeds", "n_pairs", "n_scenes", "verdict", "reason", "source", "reference_run_ids", "row_run_ids")


def _r(v: float | None, nd: int = 4):
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else round(float(v), nd)


def ordering_rows(table: FilledTable) -> Iterable[dict]:
    for ln in table.orderings:
        c, iv = ln.comparison, ln.interval
        yield {
            "table": table.spec.name, "comparison": c.text, "reference": c.ref.text, "row": c.row.text,
            "reference_variant": c.ref_variant or "", "variant": c.variant or "", "metric": ln.metric,
            "benchmark": ln.benchmark, "column_variant": ln.variant, "at": "" if ln.at is None else ln.at,
            "paper_reference": _r(ln.paper_ref), "paper_row": _r(ln.paper_row), "paper_diff": _r(ln.paper_diff),
            "ours_reference": _r(ln.ours_ref), "ours_row": _r(ln.ours_row), "ours_diff": _r(ln.ours_diff),
            "ours_diff_std": _r(ln.ours_std) if ln.n_seeds > 1 else "", "n_seeds": ln.n_seeds,
            "ci_low": _r(iv.lo) if iv else "", "ci_high": _r(iv.hi) if iv else "", "level": iv.level if iv else "",
            "n_boot": iv.n_boot if iv else "", "boot_seed": iv.seed if iv else "",
            "ci_seeds": iv.seeds_label if iv else "",
            "n_pairs": iv.n_pairs if iv else "", "n_scenes": iv.n_scenes if iv else "",
            "verdict": ln.verdict or "", "reason": ln.reason or "", "source": ln.source,
            "reference_run_ids": ";".join(ln.ref_runs), "row_run_ids": ";".join(ln.row_runs),
        }


def write_orderings_csv(table: FilledTable, path: Path) -> Path | None:
    """``<table>_orderings.csv`` (one line per tested ordering); None when the table compares nothing."""
    if not table.orderings:
        return None
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=ORDERING_FIELDS)
        w.writeheader()
        w.writerows(ordering_rows(table))
    return path
