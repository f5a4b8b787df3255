"""Figures of the results: recall against the number of sampled points (per run, written by
:mod:`pcrcg.pipeline`; per table, by :mod:`pcrcg.report`) and a table's color coverage."""

from __future__ import annotations

import re
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Mapping

from pcrcg.plots import pyplot, save_figure

if TYPE_CHECKING:  # not at run time: importing pcrcg.report.tables runs pcrcg.report, which imports this module
    from pcrcg.report.tables import FilledTable


def _n_axis(ax, sizes: list[int]) -> None:
    """The x axis of a recall plot: the sizes N evenly spaced (like a log axis, without its cost)."""
    ax.set_xticks(range(len(sizes)))
    ax.set_xticklabels([str(n) for n in sizes])
    ax.set_xlabel("# sampled points")


def _wrap(title: str, width_in: float, fontsize: float) -> tuple[str, int]:
    """``title`` broken into lines that fit a figure ``width_in`` inches wide at ``fontsize`` points (a long
    table title ran off both edges), and the number of lines."""
    chars = max(20, int(width_in * 72 / (0.55 * fontsize)))  # ~0.55 em per character of the default font
    text = textwrap.fill(title, width=chars)
    return text, text.count("\n") + 1


_KEY = re.compile(r"^(?P<bench>[^/]+)/(?P<metric>rr|fmr|ir)_(?P<n>\d+)$")


def plot_run_recall(metrics: Mapping[str, float], path: Path, title: str = "") -> Path | None:
    """One run: RR / FMR / IR (%) against sampled points, one panel per metric, a line per benchmark."""
    series: dict[str, dict[str, list[tuple[int, float]]]] = {}
    for key, v in metrics.items():
        m = _KEY.match(key)
        if m:
            series.setdefault(m["metric"], {}).setdefault(m["bench"], []).append((int(m["n"]), float(v)))
    if not series:
        return None
    plt = pyplot()
    names = [m for m in ("rr", "fmr", "ir") if m in series]
    sizes = sorted({n for m in names for pts in series[m].values() for n, _ in pts})
    pos = {n: i for i, n in enumerate(sizes)}  # where _n_axis puts each N
    fig, axes = plt.subplots(1, len(names), figsize=(4 * len(names), 3.2), squeeze=False)
    for ax, name in zip(axes[0], names):
        for bench, pts in sorted(series[name].items()):
            pts.sort()
            ax.plot([pos[p[0]] for p in pts], [p[1] for p in pts], marker="o", label=bench)
        _n_axis(ax, sizes)
        ax.set_ylabel(f"{name.upper()} (%)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.17, top=0.86, wspace=0.3)
    return save_figure(fig, path, dpi=110)


def plot_table_recall(table: FilledTable, path: Path) -> Path | None:
    """A table's recall against sampled points: ours (solid, ± std) beside the paper (dashed)."""
    panels: dict[tuple[str, str], list] = {}
    for c in table.cells:
        if c.col.n_points is not None and c.col.metric in ("RR", "FMR", "IR"):
            panels.setdefault((c.col.metric, c.col.benchmark), []).append(c)
    if not panels:
        return None
    plt = pyplot()
    keys = list(panels)
    sizes = sorted({c.col.n_points for cells in panels.values() for c in cells})
    pos = {n: i for i, n in enumerate(sizes)}
    # the legend's width from its longest label (about 0.06 inch a character at 7 pt), beside the panels
    longest = max((len(f"{r.text} (paper)") for r in table.spec.rows), default=0)
    legend_in = max(2.8, 0.06 * longest + 0.3)
    fig, axes = plt.subplots(1, len(keys), figsize=(3.6 * len(keys) + legend_in, 3.6), squeeze=False)
    # one color per row: matplotlib's 10-color cycle, 20 colors (tab20) for longer tables
    colors = (plt.rcParams["axes.prop_cycle"].by_key()["color"] if len(table.spec.rows) <= 10
              else [plt.get_cmap("tab20")(k) for k in range(20)])
    for ax, key in zip(axes[0], keys):
        cells = panels[key]
        for i, row in enumerate(table.spec.rows):
            rc = sorted((c for c in cells if c.row is row), key=lambda c: c.col.n_points)
            color = colors[i % len(colors)]
            ours = [c for c in rc if c.mean is not None]
            paper = [c for c in rc if c.paper is not None]
            if ours:
                ax.errorbar([pos[c.col.n_points] for c in ours], [c.mean for c in ours],
                            yerr=[c.std or 0.0 for c in ours], color=color, marker="o", capsize=2,
                            label=f"{row.text} (ours)")
            if paper:
                ax.plot([pos[c.col.n_points] for c in paper], [c.paper for c in paper], color=color,
                        linestyle="--", marker="x", alpha=0.7, label=f"{row.text} (paper)")
        _n_axis(ax, sizes)
        ax.set_ylabel(f"{key[0]} (%)")
        ax.set_title(key[1], fontsize=10)
        ax.grid(alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    legend_w = legend_in / fig.get_figwidth()
    if handles:
        fig.legend(handles, labels, loc="center right", fontsize=7, frameon=False)
    title, lines = _wrap(table.spec.title, fig.get_figwidth(), 9)
    fig.suptitle(title, fontsize=9)
    fig.subplots_adjust(left=0.7 / fig.get_figwidth(), right=1 - legend_w - 0.01, bottom=0.15,
                        top=0.85 - 0.045 * (lines - 1), wspace=0.35)
    return save_figure(fig, path, dpi=110)


def plot_coverage(table: FilledTable, path: Path) -> Path | None:
    """Color coverage per row (ours): the fraction of points that received a 2D feature."""
    if not table.coverage:
        return None
    plt = pyplot()
    labels = list(table.coverage)
    means = [table.coverage[k][0] for k in labels]
    stds = [table.coverage[k][1] for k in labels]
    fig, ax = plt.subplots(figsize=(max(3.5, 1.1 * len(labels)), 3.2))
    ax.bar(range(len(labels)), means, yerr=stds, capsize=3, color="#4c72b0")
    ax.set_xticks(range(len(labels)))
    ax.set_xticklabels(labels, rotation=20, ha="right", fontsize=8)
    ax.set_ylim(0, 1.0)
    ax.set_ylabel("color coverage")
    ax.set_title(_wrap(f"{table.spec.title}: color coverage", 0.8 * fig.get_figwidth(), 9)[0], fontsize=9)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)
