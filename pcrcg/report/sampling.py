"""Recall per sample size N, split by how the protocol drew each pair's N points.

Predator's protocol (``pcrcg.registration.sampling``) draws a fragment's N points by the model's scores
(overlap x matchability) only when the fragment has more than N points; a fragment with N or fewer is
drawn uniformly with replacement (``registration.fewer_points=with_replacement``) or used whole. So at
one N a benchmark mixes three regimes per pair: *scores* (both fragments sampled by the scores),
*mixed* (one of them) and *uniform* (neither). Where most pairs are uniform at an N, that column
measures the descriptors without the learned sampling, whatever the model.

At the cpu profile (6 cm model voxel) the smaller fragment of a pair has ~3.3k points, so N = 5000 is
uniform for most pairs while N <= 1000 is sampled by the scores for nearly all; at the paper's 2.5 cm
(~18k points) every N is sampled. This module measures what that does to recall, from the per-pair
outcomes a run logged (``pairs/<benchmark>.csv``) and the fragments of its data set:

* :func:`pair_regimes` ``(src_points (P,), tgt_points (P,), n) -> (P,) str``;
* :func:`regime_table` ``(pairs, points) -> DataFrame``: per N, the pairs of each regime and their recall,
  plus the recall at every N of the pairs that are uniform at the largest N (the same pairs across N);
* :func:`run_regimes` reads a tracked run's outcomes and fragments; :func:`format_table` prints one.

``python -m pcrcg.report.sampling RUN [RUN ...] [--tracking-uri URI] [--benchmarks 3DLoMatch 3DMatch]
[--prefix real-redkitchen --root data/real-redkitchen] [--out FILE.md]`` (RUN: a run id or its first
characters). Recall here is the share of counted pairs (pooled over scenes, not the protocol's mean
of scene recalls): the regimes split scenes into groups of a few pairs.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from pcrcg.errors import ConfigError

REGIMES = ("scores", "mixed", "uniform")
COLUMNS = ("n_points", "pairs", *(f"n_{r}" for r in REGIMES), "rr", *(f"rr_{r}" for r in REGIMES), "rr_fixed")


def pair_regimes(src_points: np.ndarray, tgt_points: np.ndarray, n: int) -> np.ndarray:
    """Regime of each pair at sample size ``n``: ``scores`` when both fragments have more than ``n``
    points (P,), ``uniform`` when neither has, else ``mixed``. Returns (P,) str."""
    a = np.asarray(src_points).reshape(-1) > n
    b = np.asarray(tgt_points).reshape(-1) > n
    if a.shape != b.shape:
        raise ValueError(f"src_points {a.shape} and tgt_points {b.shape} differ in length")
    return np.where(a & b, "scores", np.where(a | b, "mixed", "uniform"))


def _share(x: pd.Series) -> float:
    return 100.0 * float(x.mean()) if len(x) else float("nan")


def regime_table(pairs: pd.DataFrame, points: Mapping[tuple[str, int], int]) -> pd.DataFrame:
    """Per N of ``pairs`` (per-pair outcomes: columns scene, i, j, n_points, counted, registered; the
    evaluation's ``pairs/<benchmark>.csv``), over the counted pairs: how many are in each regime and
    the recall (%) of all, of each regime, and ``rr_fixed``: of the pairs uniform at the largest N
    (the same pairs at every N). ``points``: (scene, fragment index) -> points at the model voxel.
    Rows in decreasing N; columns :data:`COLUMNS`."""
    need = {"scene", "i", "j", "n_points", "counted", "registered"}
    if missing := need - set(pairs.columns):
        raise ValueError(f"per-pair outcomes lack the columns {sorted(missing)}")
    d = pairs[pairs["counted"].astype(int) == 1]
    if "estimate" in d.columns:  # a model's own estimates (GeoTransformer's LGR) have no N
        d = d[d["estimate"].fillna("").astype(str) == ""]
    d = d.copy()
    if d["n_points"].isna().any():
        raise ValueError("per-pair outcomes without n_points: the method has one estimate per pair, no N")
    key = list(zip(d["scene"].astype(str), d["i"].astype(int), d["j"].astype(int)))
    try:
        d["src"] = [points[(s, i)] for s, i, _ in key]
        d["tgt"] = [points[(s, j)] for s, _, j in key]
    except KeyError as e:
        raise ValueError(f"no point count for fragment {e.args[0]}") from None
    d["n_points"] = d["n_points"].astype(int)
    top = int(d["n_points"].max()) if len(d) else 0
    top_rows = d[d["n_points"] == top]
    fixed = {(s, i, j) for s, i, j, r in zip(top_rows["scene"], top_rows["i"], top_rows["j"],
                                              pair_regimes(top_rows["src"], top_rows["tgt"], top)) if r == "uniform"}
    rows = []
    for n in sorted(d["n_points"].unique(), reverse=True):
        g = d[d["n_points"] == n]
        reg = pair_regimes(g["src"].to_numpy(), g["tgt"].to_numpy(), int(n))
        ok = g["registered"].astype(float)
        in_fixed = np.array([(s, i, j) in fixed for s, i, j in zip(g["scene"], g["i"], g["j"])], dtype=bool)
        row = {"n_points": int(n), "pairs": int(len(g)), "rr": _share(ok), "rr_fixed": _share(ok[in_fixed])}
        for r in REGIMES:
            row[f"n_{r}"] = int((reg == r).sum())
            row[f"rr_{r}"] = _share(ok[reg == r])
        rows.append(row)
    return pd.DataFrame(rows, columns=list(COLUMNS))


def fragment_points(root: str | os.PathLike, voxel: float, fragments: Sequence[tuple[str, int]],
                    progress: bool = True) -> dict[tuple[str, int], int]:
    """(scene, index) -> points at ``voxel`` of each listed fragment of the data set at ``root``."""
    from tqdm import tqdm

    from pcrcg.data.layout import Layout
    from pcrcg.data.stats.collect import model_points

    layout = Layout(root)
    out: dict[tuple[str, int], int] = {}
    for scene, i in tqdm(sorted(set(fragments)), desc="fragment points", unit="fragment", disable=not progress,
                         leave=False):
        path = layout.fragment(scene, i)
        if not path.is_file():
            raise ConfigError("data.root", str(root), f"a data set holding fragment {path}")
        out[(scene, i)] = model_points(path, voxel)
    return out


def resolve_runs(client, prefixes: Sequence[str]) -> list[str]:
    """Full run ids of ``prefixes`` (a whole id or its first characters, unambiguous) in the store."""
    ids = [r.info.run_id for e in client.search_experiments() for r in
           client.search_runs([e.experiment_id], max_results=50000)]
    out = []
    for p in prefixes:
        hits = [i for i in ids if i.startswith(p)]
        if len(hits) != 1:
            raise ConfigError("RUN", p, "one run id of the store (or its first characters)" if not hits
                              else f"an unambiguous prefix ({len(hits)} runs start with it)")
        out.append(hits[0])
    return out


def run_regimes(uri: str, run_id: str, benchmarks: Sequence[str] = ("3DLoMatch", "3DMatch"),
                prefix: str | None = None, root: str | None = None, base_dir: str | os.PathLike = ".",
                progress: bool = True) -> dict[str, pd.DataFrame]:
    """:func:`regime_table` per benchmark of a tracked run: its per-pair outcomes (``[<prefix>/]pairs/``)
    and the fragments of its ``data.root`` (or ``root``: the data set ``prefix`` names), counted at its
    ``model.voxel_size``. A benchmark without outcomes is left out."""
    from pcrcg.report.outcomes import OutcomeSource

    client = _client(uri)
    params = client.get_run(run_id).data.params
    voxel = params.get("model.voxel_size")
    if voxel is None:
        raise ConfigError("RUN", run_id[:8], "a run of a learned model (it logged no model.voxel_size)")
    data_root = root or params.get("data.root")
    if data_root is None:
        raise ConfigError("--root", "null", "the data set of the run's outcomes (the run logged no data.root)")
    base = Path(base_dir)
    data_root = str(data_root if Path(data_root).is_absolute() else base / data_root)
    out: dict[str, pd.DataFrame] = {}
    runs = pd.DataFrame([{"run_id": run_id, **{f"params.{k}": v for k, v in params.items()}}])
    with OutcomeSource(uri, base, runs) as src:
        for b in benchmarks:
            df, _ = src.frame(run_id, b, prefix)
            if df is None:
                continue
            frags = [(s, int(i)) for s, i in zip(df["scene"], df["i"])] + [(s, int(j)) for s, j in zip(df["scene"], df["j"])]
            out[b] = regime_table(df, fragment_points(data_root, float(voxel), frags, progress))
    return out


def _client(uri: str):
    from pcrcg.tracking.store import client

    return client(uri)


def _f(v: float, digits: int = 1) -> str:
    return "—" if v is None or (isinstance(v, float) and np.isnan(v)) else f"{v:.{digits}f}"


def format_table(table: pd.DataFrame, title: str) -> str:
    """A markdown table of :func:`regime_table`'s rows under ``title``."""
    top = int(table["n_points"].max()) if len(table) else 0
    lines = [f"### {title}", "",
             "RR: % of the counted pairs, pooled over scenes (the report's tables average the scenes' recalls, "
             "so their figures differ).", "",
             "| N | pairs | by scores | mixed | uniform | RR | RR by scores | RR mixed | RR uniform "
             f"| RR of the pairs uniform at {top} |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in table.itertuples():
        lines.append(f"| {r.n_points} | {r.pairs} | {r.n_scores} | {r.n_mixed} | {r.n_uniform} | {_f(r.rr)} "
                     f"| {_f(r.rr_scores)} | {_f(r.rr_mixed)} | {_f(r.rr_uniform)} | {_f(r.rr_fixed)} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None, echo: Callable[[str], None] = print) -> int:
    """``python -m pcrcg.report.sampling RUN [RUN ...]``: a run's recall per N, split by how its N points were drawn."""
    p = argparse.ArgumentParser(prog="python -m pcrcg.report.sampling", description=main.__doc__)
    p.add_argument("runs", nargs="+", metavar="RUN", help="run ids of the store (or their first characters)")
    p.add_argument("--tracking-uri", default=os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db"))
    p.add_argument("--benchmarks", nargs="+", default=["3DLoMatch", "3DMatch"])
    p.add_argument("--prefix", default=None, help="outcomes logged for another data set (e.g. real-redkitchen)")
    p.add_argument("--root", default=None, help="that data set's folder (default: the run's data.root)")
    p.add_argument("--out", default=None, help="also write the tables to this markdown file")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.prefix and not args.root:
        p.error("--prefix needs --root (the folder of the data set it names)")
    try:
        ids = resolve_runs(_client(args.tracking_uri), args.runs)
        parts = []
        for rid in ids:
            tables = run_regimes(args.tracking_uri, rid, args.benchmarks, args.prefix, args.root,
                                 progress=not args.no_progress)
            if not tables:
                raise ConfigError("RUN", rid[:8], f"a run with per-pair outcomes ({'/'.join(args.benchmarks)})")
            parts += [format_table(t, f"run {rid[:8]}, {args.prefix + ' ' if args.prefix else ''}{b}")
                      for b, t in tables.items()]
    except (ConfigError, ValueError) as e:
        print(f"pcrcg.report.sampling: {e}", file=sys.stderr)
        return 2
    text = "\n".join(parts)
    echo(text)
    if args.out:
        from pcrcg.data.layout import atomic_write_text

        atomic_write_text(Path(args.out), text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
