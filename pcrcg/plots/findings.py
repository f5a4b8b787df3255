"""The findings as a forest plot (``findings.png`` beside ``findings.md``): one line per comparison and place.

Per line of the paper's claims (not the profile's targets, whose benchmark and scale differ): our
difference (a dot colored by the verdict) with its paired bootstrap interval (a bar), each seed's own
difference (small open circles: where the seeds disagree, the interval is wide), and the paper's
difference (a cross). A second panel shows the same on the real scene when the findings have one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from pcrcg.plots import pyplot, save_figure

# The findings are pcrcg.report.findings.FilledFindings / FindingLine, read by attribute: that module draws
# this figure, so importing it here (even for types) would make the two import each other.

VERDICT_COLORS = {"holds": "#2a9d55", "reversed": "#c0392b", "not resolved": "#7f7f7f", "not run": "#bbbbbb"}


def _label(fl: Any) -> str:
    at = fl.ours.at
    where = "" if at is None else (" (mean over N)" if at == "mean" else f" ({at})")
    return f"{fl.finding.label}. {fl.comparison}{where}"


def _limit(lines: Sequence[Any], real: bool) -> float:
    """Half-width of the x axis: our intervals and seeds, and the paper's differences unless one is far
    beyond ours (ICP's +67 would squeeze every other line into a few pixels; it is drawn at the edge)."""
    ours: list[float] = [2.0]
    for fl in lines:
        o = fl.real if real else fl.ours
        if o is None or o.ours_diff is None:
            continue
        ours += [abs(o.ours_diff)] + [abs(v) for v in o.by_seed.values()]
        if o.interval is not None:
            ours += [abs(o.interval.lo), abs(o.interval.hi)]
    top = max(ours)
    if real:  # the real scene has no paper numbers
        return 1.12 * top
    papers = [abs(o.paper_diff) for fl in lines if (o := fl.ours) is not None and o.paper_diff is not None]
    return 1.12 * max([top] + [v for v in papers if v <= 2 * top])


def _panel(ax: Any, lines: Sequence[Any], real: bool, title: str) -> None:
    lim = _limit(lines, real)
    for y, fl in enumerate(lines):
        o = fl.real if real else fl.ours
        verdict = (fl.real_verdict if real else fl.verdict) or "not run"
        color = VERDICT_COLORS.get(verdict, "#7f7f7f")
        if not real and o is not None and o.paper_diff is not None:
            v = o.paper_diff
            if abs(v) <= lim:
                ax.plot([v], [y], marker="x", color="black", markersize=6, linestyle="none")
            else:  # off the axis: an arrow at the edge with the paper's number
                edge = 0.97 * lim * (1 if v > 0 else -1)
                ax.plot([edge], [y], marker=">" if v > 0 else "<", color="black", markersize=5, linestyle="none")
                ax.text(edge - 0.04 * lim * (1 if v > 0 else -1), y, f"paper {v:+.0f}", va="center",
                        ha="right" if v > 0 else "left", fontsize=6,
                        bbox={"facecolor": "white", "edgecolor": "none", "pad": 0.5})
        if o is None or o.ours_diff is None or not o.ref_runs or not o.row_runs:
            ax.text(0.0, y, "  not run" if verdict == "not run" else "  —", va="center", fontsize=7, color="#888888")
            continue
        iv = o.interval
        if iv is not None:
            ax.plot([iv.lo, iv.hi], [y, y], color=color, linewidth=2.2, solid_capstyle="butt")
        ax.plot([o.ours_diff], [y], marker="o", color=color, markersize=6, linestyle="none")
        if len(o.by_seed) > 1:
            ax.plot(list(o.by_seed.values()), [y] * len(o.by_seed), marker="o", markersize=4, linestyle="none",
                    markerfacecolor="none", markeredgecolor=color, alpha=0.8)
    ax.axvline(0.0, color="black", linewidth=0.8)
    ax.set_xlim(-lim, lim)
    ax.set_ylim(len(lines) - 0.5, -0.5)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("Δ registration recall (points)", fontsize=8)
    ax.grid(axis="x", alpha=0.3)
    ax.tick_params(labelsize=7)


def plot_findings(filled: Any, path: str | Path) -> Path | None:
    """The forest plot of the claims' lines (module docstring); None when there are none."""
    lines = [ln for ln in filled.lines if not ln.finding.is_target]
    if not lines:
        return None
    plt = pyplot()
    real = filled.spec.real is not None and any(ln.real is not None for ln in lines)
    height = 0.8 + 0.24 * len(lines)
    ncols = 2 if real else 1
    fig, axes = plt.subplots(1, ncols, figsize=(4.0 * ncols + 3.6, height), sharey=True, squeeze=False)
    bench = lines[0].finding.benchmark
    _panel(axes[0][0], lines, False, f"generated {bench}: ours (dot: mean Δ, bar: 95% interval, circles: seeds)")
    if real:
        _panel(axes[0][1], lines, True, f"{filled.spec.real} {bench}")
    axes[0][0].set_yticks(range(len(lines)))
    axes[0][0].set_yticklabels([_label(ln) for ln in lines], fontsize=7)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], marker="o", color=c, linestyle="-", label=v) for v, c in VERDICT_COLORS.items()]
    handles.append(Line2D([], [], marker="x", color="black", linestyle="none", label="paper's Δ"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=7, frameon=False)
    fig.subplots_adjust(left=3.4 / fig.get_figwidth(), right=0.98, top=1 - 0.35 / height,
                        bottom=0.75 / height, wspace=0.08)
    return save_figure(fig, path, dpi=110)


def plot_training(rows: Sequence[Any], path: str | Path) -> Path | None:
    """``findings_training.png``: each run's validation feature recall over its training steps (one line per run,
    one color per job), a filled marker at each validation after which its matchability loss was on (from the
    first step: every marker filled), and the threshold of Predator's schedule (a dashed line, where a run has one).
    ``rows``: :class:`pcrcg.report.findings.TrainingRow`; None when no run has a curve."""
    rows = [r for r in rows if r.curve]
    if not rows:
        return None
    plt = pyplot()
    jobs = list(dict.fromkeys((r.experiment, r.job) for r in rows))
    cmap = plt.get_cmap("tab10")
    fig, ax = plt.subplots(figsize=(9.0, 4.2))
    labelled: set[tuple[str, str]] = set()
    for r in rows:
        key = (r.experiment, r.job)
        color = cmap(jobs.index(key) % 10)
        steps = [s for s, _ in r.curve]
        vals = [100 * v for _, v in r.curve]
        name = ", ".join(r.names)
        ax.plot(steps, vals, color=color, lw=1.2, label=None if key in labelled else name)
        labelled.add(key)
        on = set(r.on_steps) if not r.matchability or r.threshold is None or r.threshold > 0 else set(steps)
        for s, v in zip(steps, vals):
            ax.plot([s], [v], marker="o", ms=4, color=color, markerfacecolor=color if s in on else "white")
    thresholds = sorted({r.threshold for r in rows if r.threshold is not None and r.threshold > 0})
    for t in thresholds:
        ax.axhline(100 * t, color="#555555", ls="--", lw=0.8)
        ax.annotate(f"matchability loss on above {100 * t:.0f}%", (ax.get_xlim()[0], 100 * t), xytext=(4, 3),
                    textcoords="offset points", fontsize=7, color="#555555")
    ax.set_xlabel("training step")
    ax.set_ylabel("validation feature recall (%)")
    ax.set_title("How the rows' models trained (filled: matchability loss on after that validation)", fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)
