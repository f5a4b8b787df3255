"""Per-pair outcomes of an evaluation: ``pairs/<benchmark>.csv``, one line per (pair, N).

What the benchmark metrics summarise, kept pair by pair so that the report can compare two
methods on the same test pairs (a paired bootstrap, :mod:`pcrcg.report.stats`)::

    scene,i,j,n_points,counted,present,registered,error,rre,rte,inlier_ratio,estimate

* ``n_points``: the sample size N of a learned model's estimates (``<est_dir>/<N>/<scene>/est.log``);
  empty for a classical method (``<est_dir>/<scene>/est.log``) and for a model's own estimates.
* ``estimate``: which of a model's own estimates the row scores (:data:`OWN_ESTIMATES`,
  ``<est_dir>/lgr/<scene>/est.log``: GeoTransformer's LGR, and RANSAC on its point pairs); empty
  for the N of Predator's protocol and for a classical method. Files written before this column
  existed lack it: read them with an empty ``estimate``.
* ``counted`` (0/1): the pair counts in the registration recall (``counted_mask``: not adjacent,
  and Predator's variant when configured); ``present``: an estimate exists; ``registered``:
  present and ``error <= rmse_threshold**2``; ``error``, ``rre`` (deg), ``rte`` (m): from
  :func:`pcrcg.evaluation.metrics.score_scene` (empty when there is no estimate).
* ``inlier_ratio`` (0..1): from ``<est_dir>/<N>/<scene>/inlier_ratios.txt`` when the evaluation
  wrote it (:func:`pcrcg.evaluation.model.evaluate_model_outputs` does), else empty.

Nothing is computed differently from the metrics: the outcomes are :func:`score_scene` on the
``est.log`` files that the run keeps as artifacts, so the scene-averaged mean of ``registered``
over ``counted`` pairs is the run's ``<benchmark>/rr_<N>`` (the report checks that).
Same estimates, same bytes. :func:`pair_artifacts` is the evaluation stage's hook.
"""

from __future__ import annotations

import csv
import logging
import math
import os
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from pcrcg.evaluation.metrics import RMSE_THRESHOLD, SceneGT, load_estimates, score_scene

log = logging.getLogger(__name__)

PAIR_COLUMNS = ("scene", "i", "j", "n_points", "counted", "present", "registered", "error", "rre", "rte",
                "inlier_ratio", "estimate")
# a model's own registration (PairOutput.estimate, GeoTransformer's LGR), scored beside the N of Predator's
# protocol as "N": its estimate (lgr) and the configured RANSAC on its point pairs (lgr_ransac)
OWN_ESTIMATES = ("lgr", "lgr_ransac")
INLIER_RATIO_FILE = "inlier_ratios.txt"
PAIRS_FOLDER = "pairs"


def _num(v: float) -> str:
    """Compact, deterministic text of a float (empty for NaN)."""
    return "" if v is None or not math.isfinite(float(v)) else f"{float(v):.6g}"


# --------------------------------------------------------------------------- inlier ratios beside est.log


def write_inlier_ratios(path: str | os.PathLike, gt: SceneGT, ratios: Mapping[tuple[int, int], float]) -> None:
    """``i j inlier_ratio`` per line in ``gt.log`` order (pairs without a value left out)."""
    lines = [f"{p.i} {p.j} {float(ratios[(p.i, p.j)]):.6g}\n" for p in gt.pairs if (p.i, p.j) in ratios]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(lines))


def read_inlier_ratios(path: str | os.PathLike) -> dict[tuple[int, int], float]:
    out: dict[tuple[int, int], float] = {}
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        if len(parts) == 3:
            out[(int(parts[0]), int(parts[1]))] = float(parts[2])
    return out


# --------------------------------------------------------------------------- outcomes


def pair_rows(
    gt: Mapping[str, SceneGT],
    estimates: Mapping[str, Mapping[tuple[int, int], np.ndarray]],
    n_points: int | None = None,
    *,
    estimate: str = "",
    predator_variant: bool = False,
    threshold: float = RMSE_THRESHOLD,
    inlier_ratios: Mapping[str, Mapping[tuple[int, int], float]] | None = None,
    only_present: bool = False,
) -> list[dict[str, Any]]:
    """One row (``PAIR_COLUMNS``) per ``gt.log`` pair, scored with :func:`score_scene`.

    ``n_points``: the N of the estimates; ``estimate``: or which own estimate they are (one of
    :data:`OWN_ESTIMATES`, with ``n_points`` None).

    ``only_present``: leave out pairs without an estimate (a ``max_pairs`` subset, which the
    metrics score alone); otherwise such a pair is a counted failure, as in the metrics.
    """
    rows = []
    for s in sorted(gt):
        g = gt[s]
        sc = score_scene(g, estimates.get(s, {}), predator_variant, threshold)
        irs = (inlier_ratios or {}).get(s, {})
        for k, p in enumerate(g.pairs):
            if only_present and not sc.present[k]:
                continue
            rows.append({
                "scene": s, "i": p.i, "j": p.j, "n_points": "" if n_points is None else int(n_points),
                "counted": int(sc.counted[k]), "present": int(sc.present[k]), "registered": int(sc.success[k]),
                "error": _num(sc.error[k]), "rre": _num(sc.rre[k]), "rte": _num(sc.rte[k]),
                "inlier_ratio": _num(irs[(p.i, p.j)]) if (p.i, p.j) in irs else "", "estimate": estimate,
            })
    return rows


def estimate_dirs(est_dir: str | os.PathLike, only: str | None = None) -> list[tuple[int | None, str, Path]]:
    """``[(N, own estimate, folder)]`` of an estimate folder: a learned model's ``<N>/`` folders (largest N
    first, own estimate ``""``) and its ``lgr/``, ``lgr_ransac/`` ones (N None); a classical method's
    ``[(None, "", est_dir)]``. ``only``: just that own estimate's folder (``[]`` if absent)."""
    est_dir = Path(est_dir)
    subs = [d for d in est_dir.iterdir() if d.is_dir() and not (d / "est.log").is_file()]  # not scene folders
    sizes = sorted(((int(d.name), "", d) for d in subs if d.name.isdigit()), key=lambda t: -t[0])
    own = [(None, d.name, d) for name in OWN_ESTIMATES for d in subs if d.name == name]
    if only is not None:
        return [t for t in own if t[1] == only]
    return sizes + own if sizes or own else [(None, "", est_dir)]


def rows_from_estimate_dir(
    gt: Mapping[str, SceneGT],
    est_dir: str | os.PathLike,
    *,
    predator_variant: bool = False,
    threshold: float = RMSE_THRESHOLD,
    only_present: bool = False,
    only: str | None = None,
) -> list[dict[str, Any]]:
    """Per-pair rows of every N and own estimate of an estimate folder (``<N>/<scene>/est.log``,
    ``lgr/<scene>/est.log`` or ``<scene>/est.log``; ``only``: just that own estimate, see
    :func:`estimate_dirs`).

    A scene without ``est.log`` fails all its pairs, as in :func:`score_directories`.
    """
    rows: list[dict[str, Any]] = []
    for n, own, d in estimate_dirs(est_dir, only):
        est, _ = load_estimates(d, gt.keys())
        irs = {s: read_inlier_ratios(d / s / INLIER_RATIO_FILE) for s in gt if (d / s / INLIER_RATIO_FILE).is_file()}
        rows += pair_rows(gt, est, n, estimate=own, predator_variant=predator_variant, threshold=threshold,
                          inlier_ratios=irs, only_present=only_present)
    return rows


def write_pair_csv(path: str | os.PathLike, rows: Iterable[Mapping[str, Any]]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=PAIR_COLUMNS, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    return path


def pair_artifacts(
    out_dir: str | os.PathLike,
    gts: Mapping[str, Mapping[str, SceneGT]],
    artifacts: Sequence[tuple[Path, str | None]],
    predator_variant: bool = False,
    thresholds: Mapping[str, float] | None = None,
    only_present: bool = False,
) -> list[tuple[Path, str]]:
    """The evaluation stage's hook: ``<out_dir>/pairs/<benchmark>.csv`` from the ``estimates/<benchmark>``
    folders among ``artifacts``; returns ``[(<out_dir>/pairs, "pairs")]`` to log (``[]`` if none).

    Never raises: the per-pair file is for the report's intervals, and a run must not fail for it
    (a warning names what went wrong; the report then recomputes from ``est.log`` or says why not).
    """
    th = float((thresholds or {}).get("rmse_threshold", RMSE_THRESHOLD))
    folder = Path(out_dir) / PAIRS_FOLDER
    written = False
    for path, name in artifacts:
        if not name or not str(name).startswith("estimates/"):
            continue
        b = str(name).split("/", 1)[1]
        if b not in gts:
            continue
        try:
            rows = rows_from_estimate_dir(gts[b], path, predator_variant=predator_variant, threshold=th,
                                          only_present=only_present)
            write_pair_csv(folder / f"{b}.csv", rows)
            written = True
        except Exception as e:  # noqa: BLE001 - see docstring
            log.warning("per-pair outcomes of %s not written (%s: %s)", b, type(e).__name__, e)
    return [(folder, PAIRS_FOLDER)] if written else []
