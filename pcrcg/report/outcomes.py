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
   likewise a model's own estimate (``<b>/rr_lgr``, ``rr_lgr_ransac``: GeoTransformer's LGR) that the
   run's pairs file lacks (files written before the ``estimate`` column), from
   ``[<prefix>/]estimates/<b>/lgr/`` and the gt files under ``data.root`` or, for a prefix, the root
   named by the run's ``<prefix>.data_root`` tag (written by ``mode=tracked``);
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
_KEY = re.compile(r"^(?P<bench>[^/]+)/(?P<metric>rr|fmr)(?:_(?P<n>\d+|lgr|lgr_ransac))?$")


@dataclass
class Outcomes:
    """One run's outcome per pair (index: ``(scene, i, j)``), or why there is none."""

    values: pd.Series | None
    source: str = ""
    reason: str | None = None


def parse_key(key: str) -> tuple[str, str, int | str | None] | None:
    """``3DLoMatch/rr_1000`` -> (``3DLoMatch``, ``RR``, 1000); ``3DMatch/rr`` -> (..., None);
    ``3DMatch/rr_lgr`` -> (..., ``"lgr"``: a model's own estimate, ``OWN_ESTIMATES``); else None."""
    m = _KEY.match(key or "")
    if not m:
        return None
    n = m["n"]
    return m["bench"], m["metric"].upper(), (int(n) if n.isdigit() else n) if n else None


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

    def _param(self, run_id: str, key: str, default: Any = None, kind: str = "params") -> Any:
        rec = self.params.get(run_id)
        v = None if rec is None else rec.get(f"{kind}.{key}")
        return default if v is None or (isinstance(v, float) and math.isnan(v)) else v

    def metric_history(self, run_id: str, key: str) -> list[tuple[int, float]]:
        """Every logged value of metric ``key`` of a run as (step, value), in step order ([] when it has none or
        the store cannot be read)."""
        try:
            hist = self.client.get_metric_history(run_id, key)
        except Exception:  # noqa: BLE001 - an unreachable store: no curve
            return []
        return sorted((int(m.step), float(m.value)) for m in hist)

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
    def frame(self, run_id: str, benchmark: str, prefix: str | None = None,
              own: str | None = None) -> tuple[pd.DataFrame | None, str]:
        """(per-pair rows of ``[<prefix>/]pairs/<benchmark>.csv``, where they came from) or (None, why not);
        ``own`` (``lgr``, ``lgr_ransac``): the rows of that own estimate recomputed from its est.log files."""
        key = (run_id, prefix or "", benchmark, own or "")
        if key not in self._frames:
            try:
                self._frames[key] = (self._recompute(run_id, benchmark, prefix, own) if own
                                     else self._load(run_id, benchmark, prefix))
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
        return self._recompute(run_id, benchmark)

    def _data_root(self, run_id: str, prefix: str | None) -> tuple[Path | None, str]:
        """The data set whose gt files score the run's estimates: ``data.root`` (its own) or the root of
        the ``<prefix>.data_root`` tag (``<root> params_hash=<hash>``); (None, why not) otherwise."""
        if prefix:
            tag = self._param(run_id, f"{prefix}.data_root", kind="tags")
            if tag is None:
                return None, f"run {run_id[:8]} has no {prefix}.data_root tag to find the benchmark's gt files"
            root = str(tag).split(" params_hash=", 1)[0].strip()
        else:
            root = self._param(run_id, "data.root")
            if root is None:
                return None, f"run {run_id[:8]} has est.log files but no data.root param to find the benchmark's gt files"
        path = Path(str(root))
        return (path if path.is_absolute() else self.base / path), ""

    def _recompute(self, run_id: str, benchmark: str, prefix: str | None = None,
                   own: str | None = None) -> tuple[pd.DataFrame | None, str]:
        """Per-pair rows scored from the run's ``[<prefix>/]estimates/<benchmark>[/<own>]`` est.log files."""
        est = f"{prefix}/estimates/{benchmark}" if prefix else f"estimates/{benchmark}"
        listed = self._listed(run_id, est)
        what = f"{est}/{own}" if own else est
        if not listed or (own and what not in listed):
            name = pairs_artifact(benchmark, prefix)
            return None, (f"run {run_id[:8]} logged neither per-pair outcomes ({name}) nor est.log files "
                          f"({what}/); rerun it to get an interval")
        root, why = self._data_root(run_id, prefix)
        if root is None:
            return None, why
        from pcrcg.data.layout import Layout

        bench_dir = Layout(root).benchmark_dir(benchmark)
        if not bench_dir.is_dir():
            return None, (f"run {run_id[:8]} predates the per-pair file and its benchmark files ({bench_dir}) "
                          f"are not here to recompute it from its est.log files")
        from pcrcg.evaluation.metrics import load_benchmark
        from pcrcg.evaluation.pairs import PAIR_COLUMNS, rows_from_estimate_dir

        gt = load_benchmark(bench_dir)
        local = self._download(run_id, what)
        max_pairs = str(self._param(run_id, "eval.max_pairs", "null")).strip().lower()
        rows = rows_from_estimate_dir(
            gt, local.parent if own else local,
            predator_variant=_flag(self._param(run_id, "eval.predator_variant", False)),
            threshold=float(self._param(run_id, "eval.rmse_threshold", 0.2)),
            only_present=max_pairs not in ("null", "none", ""),
            only=own,
        )
        df = pd.DataFrame(rows, columns=list(PAIR_COLUMNS))
        return _typed(df), f"recomputed from the run's {what} est.log files and {bench_dir}"

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
        if isinstance(n, str):  # a model's own estimate: its rows, else recomputed from its est.log files
            sel = df[df["estimate"] == n] if df is not None else df
            if sel is None or sel.empty:
                df, source = self.frame(run_id, bench, prefix, own=n)
                if df is None:
                    return Outcomes(None, reason=source)
                sel = df[df["estimate"] == n]
        elif df is None:
            return Outcomes(None, reason=source)
        else:
            sel = df[df["estimate"] == ""]
            sel = sel[sel["n_points"].isna()] if n is None else sel[sel["n_points"] == n]
        if sel.empty:
            return Outcomes(None, reason=f"run {run_id[:8]}: no per-pair outcomes at "
                                         f"{_what(n)} ({source})")
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


def _what(n: int | str | None) -> str:
    return "its only sample size" if n is None else f"its own estimate {n}" if isinstance(n, str) else f"{n} points"


def _typed(df: pd.DataFrame) -> pd.DataFrame:
    df = df.copy()
    # files written before the column existed have no own estimates: every row is an N (or the only one)
    df["estimate"] = df["estimate"].fillna("").astype(str) if "estimate" in df.columns else ""
    for c in ("n_points", "error", "rre", "rte", "inlier_ratio"):
        df[c] = pd.to_numeric(df[c].replace("", np.nan), errors="coerce")
    for c in ("i", "j", "counted", "present", "registered"):
        df[c] = df[c].astype(int)
    df["scene"] = df["scene"].astype(str)
    return df


def _read_pairs(path: Path) -> pd.DataFrame:
    return _typed(pd.read_csv(path, dtype={"scene": str}, keep_default_na=True))
