"""Figures, in one place: the run's and the tables' recall against N (:mod:`pcrcg.plots.recall`), the
color-coverage figure (:mod:`pcrcg.plots.coverage`), the findings' forest plot (:mod:`pcrcg.plots.findings`),
pictures of a data set (:mod:`pcrcg.plots.data`;
:mod:`pcrcg.data.stats` draws its side-by-side fragments with the helpers below).

The helpers every figure uses: :func:`pyplot` (matplotlib on the Agg backend, imported only when a
figure is drawn), :func:`save_figure` (parent folder made, figure written and closed) and
:func:`no_ticks`. Nothing here computes a result (``plots`` is outside the code version,
:data:`pcrcg.tracking.git.NOT_RESULT_CODE`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | Path, dpi: float | None = None) -> Path:
    """Write ``fig`` to ``path`` (its folder made first) at ``dpi`` (None: matplotlib's ``savefig.dpi``,
    the figure's own unless set otherwise) and close it; the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path


def no_ticks(ax: Any) -> None:
    """An axes without ticks (pictures, not plots)."""
    ax.set_xticks([])
    ax.set_yticks([])
