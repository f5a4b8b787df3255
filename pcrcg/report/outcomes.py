"""Per-pair outcomes of tracked runs, for the paired bootstrap of the report's orderings.

Where they come from, per run and benchmark, in this order:

1. the run's ``pairs/<benchmark>.csv`` artifact (written by the evaluation stage,
   :mod:`pcrcg.evaluation.pairs`); for a metric of another data set evaluated on the same run,
   ``<prefix>/<benchmark>/rr_<N>`` (e.g. ``real-redkitchen/3DLoMatch/rr_5000``, logged by
   ``python -m pcrcg.evaluate mode=tracked name=<prefix>``), its ``<prefix>/pairs/<benchmark>.csv``
   (same format), and nothing else (step 2 needs the run's own data set);
2. for runs logged before that file existed: recomputed with the same code from the run's
   ``estimates/<benchmark>`` artifacts (``est.log`` files) and the benchmark's ``gt.log`` /
   ``gt.info`` under the run's ``data.root`` (relative to the folder the report starts in);
3. otherwise nothing, with the reason.

Every outcome vector is checked against the metric the run logged (the scene-averaged mean of
the outcomes must be the run's ``<benchmark>/rr_<N>`` or ``fmr_<N>``): a recomputation against
benchmark files that were regenerated since the run is refused, not silently used.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pcrcg.report.stats import recall

# logged metric value vs. the recall recomputed from the per-pair outcomes (percentage points)
TOLERANCE = 1e-6
FMR_THRESHOLD = 0.05
_KEY = re.compile(r"^(?P<bench>[^/]+)/(?P<metric>rr|fmr)(?:_(?P<n>\d+))?$")


@dataclass
class Outcomes:
    """One run's outcome per pair (index: ``(scene, i, j)``), or why there is none."""

    values: pd.Series | None
    source: str = ""
    reason: str | None = None


def parse_key(key: str) -> tuple[str, str, int | None] | None:
    """``3DLoMatch/rr_1000`` -> (``3DLoMatch``, ``RR``, 1000); ``3DMatch/rr`` -> (..., None); else None."""
    m = _KEY.match(key or "")
    if not m:
        return None
    return m["bench"], m["metric"].upper(), int(m["n"]) if m["n"] else None


def split_prefix(key: str) -> tuple[str | None, str]:
    """``real-redkitchen/3DLoMatch/rr_5000`` -> (``real-redkitchen``, ``3DLoMatch/rr_5000``); a key of
    the run's own data set (``3DLoMatch/rr_5000``) -> (None, the key)."""
    parts = (key or "").rsplit("/", 2)
    if len(parts) < 3 or not parts[0]:
        return None, key
    return parts[0], f"{parts[1]}/{parts[2]}"


def pairs_artifact(benchmark: str, prefix: str | None = None) -> str:
    """Artifact path of a run's per-pair outcomes on ``benchmark`` (of the data set ``prefix``; None: its own)."""
    return f"{prefix}/pairs/{benchmark}.csv" if prefix else f"pairs/{benchmark}.csv"


def _flag(v: Any) -> bool:
    return str(v).strip().lower() in ("true", "1", "yes")


class OutcomeSource:
    """Fetches and caches per-pair outcomes of the runs of one report (see module docstring)."""

    def __init__(self, uri: str, base_dir: str | Path, runs: pd.DataFrame):
        self.uri = uri
        self.base = Path(base_dir)
        self.params: dict[str, pd.Series] = {str(r["run_id"]): r for _, r in runs.iterrows()} if len(runs) else {}
        self._frames: dict[tuple[str, str], tuple[pd.DataFrame | None, str]] = {}
        self._tmp: Path | None = None
        self._client = None

    # ------------------------------------------------------------------ plumbing
    @property
    def client(self):
        if self._client is None:
            from pcrcg.tracking.store import client

            self._client = client(self.uri)
        return self._client

    @property
    def tmp(self) -> Path:
        if self._tmp is None:
            self._tmp = Path(tempfile.mkdtemp(prefix="pcrcg-report-"))
        return self._tmp

    def close(self) -> None:
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    def __enter__(self) -> "OutcomeSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _param(self, run_id: str, key: str, default: Any = None) -> Any:
        rec = self.params.get(run_id)
        v = None if rec is None else rec.get(f"params.{key}")
        return default if v is None or (isinstance(v, float) and math.isnan(v)) else v

    def _listed(self, run_id: str, path: str) -> list[str]:
        try:
            return [f.path for f in self.client.list_artifacts(run_id, path)]
        except Exception:  # noqa: BLE001 - an unreachable artifact store: no per-pair data
            return []

    def _download(self, run_id: str, path: str) -> Path:
        dst = self.tmp / run_id
        dst.mkdir(parents=True, exist_ok=True)
        key, old = "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", os.environ.get("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR")
        os.environ[key] = "false"  # one bar per file would flood the report's output
        try:
            return Path(self.client.download_artifacts(run_id, path, str(dst)))
        finally:
            if old is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = old

    # ------------------------------------------------------------------ per-pair table of a run
    def frame(self, run_id: str, benchmark: str, prefix: str | None = None) -> tuple[pd.DataFrame | None, str]:
        """(per-pair rows of ``[<prefix>/]pairs/<benchmark>.csv``, where they came from) or (None, why not)."""
        key = (run_id, prefix or "", benchmark)
        if key not in self._frames:
            try:
                self._frames[key] = self._load(run_id, benchmark, prefix)
            except Exception as e:  # noqa: BLE001 - reported in the table, never fatal
                self._frames[key] = (None, f"per-pair outcomes of run {run_id[:8]} unreadable "
                                           f"({type(e).__name__}: {e})")
        return self._frames[key]

    def _load(self, run_id: str, benchmark: str, prefix: str | None = None) -> tuple[pd.DataFrame | None, str]:
        name = pairs_artifact(benchmark, prefix)
        if name in self._listed(run_id, name.rsplit("/", 1)[0]):
            return _read_pairs(self._download(run_id, name)), (
                f"the run's {prefix} pairs artifact" if prefix else "the run's pairs artifact")
        if prefix:
            return None, (f"run {run_id[:8]} logged no per-pair outcomes on {prefix} ({name}); evaluate it "
                          f"again with python -m pcrcg.evaluate mode=tracked ... name={prefix}")
        est = f"estimates/{benchmark}"
        if not self._listed(run_id, est):
            return None, (f"run {run_id[:8]} logged neither per-pair outcomes ({name}) nor est.log files "
                          f"({est}/); rerun it to get an interval")
        root = self._param(run_id, "data.root")
        if root is None:
            return None, f"run {run_id[:8]} has est.log files but no data.root param to find the benchmark's gt files"
        from pcrcg.data.layout import Layout

        root = Path(str(root))
        bench_dir = Layout(root if root.is_absolute() else self.base / root).benchmark_dir(benchmark)
        if not bench_dir.is_dir():
            return None, (f"run {run_id[:8]} predates the per-pair file and its benchmark files ({bench_dir}) "
                          f"are not here to recompute it from its est.log files")
        from pcrcg.evaluation.metrics import load_benchmark
        from pcrcg.evaluation.pairs import rows_from_estimate_dir

        gt = load_benchmark(bench_dir)
        max_pairs = str(self._param(run_id, "eval.max_pairs", "null")).strip().lower()
        rows = rows_from_estimate_dir(
            gt, self._download(run_id, est),
            predator_variant=_flag(self._param(run_id, "eval.predator_variant", False)),
            threshold=float(self._param(run_id, "eval.rmse_threshold", 0.2)),
            only_present=max_pairs not in ("null", "none", ""),
        )
        from pcrcg.evaluation.pairs import PAIR_COLUMNS

        df = pd.DataFrame(rows, columns=list(PAIR_COLUMNS))
        return _typed(df), f"recomputed from the run's est.log files and {bench_dir}"

    # ------------------------------------------------------------------ outcome vectors
    def outcomes(self, run_id: str, metric_key: str, logged: float | None) -> Outcomes:
        """The run's per-pair outcome (0/1) for ``metric_key`` (``[<prefix>/]<b>/rr[_N]``, ``.../fmr[_N]``),
        checked against the ``logged`` value of that metric."""
        prefix, own_key = split_prefix(metric_key)
        parsed = parse_key(own_key)
        if parsed is None:
            return Outcomes(None, reason=f"no per-pair statistic for {metric_key} (registration and "
                                         f"feature-matching recall only)")
        bench, metric, n = parsed
        df, source = self.frame(run_id, bench, prefix)
        if df is None:
            return Outcomes(None, reason=source)
        sel = df[df["n_points"].isna()] if n is None else df[df["n_points"] == n]
        if sel.empty:
            return Outcomes(None, reason=f"run {run_id[:8]}: no per-pair outcomes at "
                                         f"{'its only sample size' if n is None else f'{n} points'} ({source})")
        if metric == "RR":
            sel = sel[sel["counted"] == 1]
            vals = sel["registered"].astype(float)
        else:
            sel = sel[sel["inlier_ratio"].notna()]
            if sel.empty:
                return Outcomes(None, reason=f"run {run_id[:8]} recorded no per-pair inlier ratios "
                                             f"(classical methods and runs before they were written)")
            thr = float(self._param(run_id, "eval.fmr_threshold", FMR_THRESHOLD))
            vals = (sel["inlier_ratio"] > thr).astype(float)
        s = pd.Series(vals.to_numpy(), index=pd.MultiIndex.from_arrays(
            [sel["scene"].astype(str), sel["i"].astype(int), sel["j"].astype(int)], names=("scene", "i", "j")))
        s = s.sort_index()
        if logged is not None and math.isfinite(logged):
            ours = recall(s.to_numpy(), s.index.get_level_values("scene"))
            if not abs(ours - logged) <= TOLERANCE * max(1.0, abs(logged)):
                return Outcomes(None, source, reason=(
                    f"run {run_id[:8]}: per-pair outcomes give {metric_key} = {ours:.4f}, the run logged "
                    f"{logged:.4f} ({source}; benchmark files regenerated since the run?)"))
        return Outcomes(s, source)


def _typed(df: pd.DataFrame) -> pd.DataFrame:
    df = df.copy()
    for c in ("n_points", "error", "rre", "rte", "inlier_ratio"):
        df[c] = pd.to_numeric(df[c].replace("", np.nan), errors="coerce")
    for c in ("i", "j", "counted", "present", "registered"):
        df[c] = df[c].astype(int)
    df["scene"] = df["scene"].astype(str)
    return df


def _read_pairs(path: Path) -> pd.DataFrame:
    return _typed(pd.read_csv(path, dtype={"scene": str}, keep_default_na=True))
