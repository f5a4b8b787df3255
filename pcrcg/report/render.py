"""Write a filled table as Markdown, LaTeX and CSV, in the paper's layout.

Each row of the paper becomes up to three lines: the paper's numbers, ours (mean ± std
over seeds) and the difference (ours − paper). A missing number of ours is a dash with a
numbered note giving the reason; the runs behind every cell are listed under the table
(run id, config hash, git sha, profile, seed) and in the CSV, one line per cell.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Iterable

from pcrcg.report.spec import LOWER_IS_BETTER, Column
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


def _col_header(col: Column) -> str:
    parts = [p for p in (col.label or col.variant, col.benchmark, str(col.n_points) if col.n_points else "") if p]
    return " ".join(parts)


def _sections(table: FilledTable) -> list[tuple[str, list[Column]]]:
    out: list[tuple[str, list[Column]]] = []
    for col in table.spec.columns:
        if not out or out[-1][0] != col.section:
            out.append((col.section, []))
        out[-1][1].append(col)
    return out


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
        out.append(f"**{section}**")
        out.append("")
        out.append("| | " + " | ".join(_col_header(c) for c in cols) + " |")
        out.append("|---|" + "---:|" * len(cols))
        for label, texts in _lines(table, cols, notes):
            out.append(f"| {label} | " + " | ".join(texts) + " |")
        out.append("")
    if notes.items:
        out.append("Missing numbers:")
        out.append("")
        out += [f"{i}. {r}" for i, r in enumerate(notes.items, 1)]
        out.append("")
    if table.protocol:
        out.append("Protocol of these runs: " + "; ".join(table.protocol))
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
    return s.replace("±", r"$\pm$").replace("Δ", r"$\Delta$").replace("−", "$-$").replace(DASH, "--")


def to_latex(table: FilledTable) -> str:
    spec = table.spec
    cols_all = list(spec.columns)
    notes = _Notes()
    out = ["% generated by python -m pcrcg.report; ours: mean $\\pm$ std over seeds",
           r"\begin{table}[h]", r"\centering", f"\\caption{{{latex_escape(spec.title)}}}",
           r"\begin{tabular}{l|" + "c" * len(cols_all) + "}", r"\toprule"]
    # header: benchmark spans, then sample sizes / labels
    spans: list[tuple[str, int]] = []
    for c in cols_all:
        key = " ".join(p for p in (c.label or c.variant, c.benchmark) if p)
        if spans and spans[-1][0] == key and c.n_points is not None:
            spans[-1] = (key, spans[-1][1] + 1)
        else:
            spans.append((key, 1))
    if any(c.n_points is not None for c in cols_all):
        out.append(" & " + " & ".join(f"\\multicolumn{{{n}}}{{c}}{{\\textbf{{{latex_escape(k)}}}}}" for k, n in spans)
                   + r" \\")
        out.append(r"\# Sampled Points & " + " & ".join(str(c.n_points or "") for c in cols_all) + r" \\")
    else:
        out.append(" & " + " & ".join(latex_escape(_col_header(c)) for c in cols_all) + r" \\")
    out.append(r"\midrule")
    for section, cols in _sections(table):
        if len(_sections(table)) > 1 or cols_all[0].n_points is not None:
            out.append(f"& \\multicolumn{{{len(cols_all)}}}{{c}}{{\\textit{{{latex_escape(section)}}}}} \\\\")
            out.append(r"\midrule")
        # a section covers a subset of columns: pad the others
        idx = [cols_all.index(c) for c in cols]
        for label, texts in _lines(table, cols, notes):
            row = [""] * len(cols_all)
            for i, t in zip(idx, texts):
                row[i] = latex_escape(t)
            out.append(latex_escape(label) + " & " + " & ".join(row) + r" \\")
        out.append(r"\midrule")
    out[-1] = r"\bottomrule"
    out += [r"\end{tabular}", r"\end{table}"]
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
