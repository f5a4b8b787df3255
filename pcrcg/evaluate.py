"""`python -m pcrcg.evaluate mode=score|pair|benchmark|tracked ...` (config: conf/evaluate.yaml).

* ``mode=score benchmark_dir=DIR estimate_dir=DIR``: score ``<estimate_dir>/<scene>/est.log``
  against ``<benchmark_dir>/<scene>/gt.log|gt.info`` (a missing estimate is a failure).
* ``mode=pair method=fpfh|icp|color_icp|sift_dlt|sift_lifted source=FILE target=FILE``: register one pair;
  ``method=learned checkpoint=FILE``: with a trained model (Predator, or PCR-CG with the
  fragments' RGB-D views in ``source_views``/``target_views``), in eval mode.
* ``mode=benchmark method=... data.root=DIR``: a classical method over the test benchmarks of a
  data set in the 3DMatch layout; writes ``<out_dir>/<benchmark>/<scene>/est.log`` and
  ``<out_dir>/metrics.json``. ``method=learned checkpoint=FILE``: a trained model, evaluated as a
  run evaluates it (every N of ``registration.n_points``; color models read the fragments' views);
  writes ``<out_dir>/<benchmark>/<N>/<scene>/est.log`` and prints RR/FMR/IR per benchmark and N.
* ``mode=tracked experiments=[main_results,window_size] data.root=DIR name=NAME``: every FINISHED run of
  those MLflow experiments (store: ``logger.tracking_uri``, ``$MLFLOW_TRACKING_URI``, ``sqlite:///mlflow.db``)
  that trained a model, evaluated on the test benchmarks of ``data.root`` with its own logged config
  (every N, seed, RANSAC, every pair) and model (its checkpoint artifact, else the cache entry whose
  ``source.json`` names it), logged into the same run: metrics ``NAME/<benchmark>/<key>``, artifacts
  ``NAME/pairs/<benchmark>.csv`` and ``NAME/estimates/<benchmark>``, tag ``NAME.data_root``. A run that
  already has ``NAME/`` metrics is skipped (``force=true`` redoes it), one whose checkpoint is gone is
  reported and skipped; ``run_ids=[...]`` restricts it to some runs (:mod:`pcrcg.evaluation.tracked`).
  The JSON lists ``evaluated``, ``skipped`` and ``failed`` runs (exit 1 when one failed).

The last line of standard output is one JSON object. Every input is checked before work starts;
a bad file is an error that names it.

Results that look like numbers but mean nothing come with a warning on standard error and in the
JSON (``warnings``, and a flag): ``mode=score`` where no estimate matched a pair of the benchmark
(an empty ``est.log``, swapped ``i j``, the wrong benchmark: ``no_estimate_matched``); ``mode=pair``
with fewer points than a registration needs (``few_points``; fewer than RANSAC's 3 is an error), a
cloud whose extent is far from a scan in metres (``scale_suspect``: km or mm units), and coordinates
so far from the origin that float32 loses precision (UTM): both clouds are then shifted to a local
origin (``origin_shift``) and the returned transform is shifted back to the original coordinates.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from pcrcg.device import cpu_threads, keep_freed_memory
from pcrcg.errors import ConfigError, DataError, PcrcgError
from pcrcg.evaluation.pairs import OWN_ESTIMATES

MODES = ("score", "pair", "benchmark", "tracked")


def _need(cfg: DictConfig, key: str, what: str) -> str:
    v = OmegaConf.select(cfg, key)
    if v is None or str(v) == "":
        raise ConfigError(key, v, what)
    return str(v)


def _existing(path: str, what: str, folder: bool = False) -> Path:
    p = Path(path)
    ok = p.is_dir() if folder else p.is_file()
    if not ok:
        raise DataError(p, f"{what} does not exist")
    return p


# mode=pair: RANSAC draws 3 correspondences; below FEW_POINTS points a transform means little; a
# scan in metres spans SCALE_RANGE; beyond FLOAT32_SAFE m from the origin float32 spacing exceeds 1 mm
MIN_POINTS = 3
FEW_POINTS = 100
SCALE_RANGE = (0.05, 1000.0)
FLOAT32_SAFE = 1.0e4


def _warn(warnings: list[str], text: str) -> None:
    warnings.append(text)
    print(f"pcrcg.evaluate: warning: {text}", file=sys.stderr, flush=True)


def run_score(cfg: DictConfig) -> dict[str, Any]:
    from pcrcg.evaluation.metrics import load_benchmark, load_estimates, score_benchmark

    bdir = _existing(_need(cfg, "benchmark_dir", "a folder of <scene>/gt.log|gt.info"), "benchmark folder", True)
    edir = _existing(_need(cfg, "estimate_dir", "a folder of <scene>/est.log"), "estimate folder", True)
    gt = load_benchmark(bdir)
    est, missing = load_estimates(edir, gt.keys())
    score = score_benchmark(gt, est, bool(cfg.predator_variant), missing, float(cfg.eval.rmse_threshold))
    pairs = {s: {(p.i, p.j) for p in g.pairs} for s, g in gt.items()}
    matched = sum(len(pairs[s] & set(e)) for s, e in est.items())
    unmatched = sum(len(set(e) - pairs[s]) for s, e in est.items())
    swapped = sum(len({(j, i) for i, j in e} & pairs[s] - set(e)) for s, e in est.items())
    n_pairs = sum(len(p) for p in pairs.values())
    warnings: list[str] = []
    if matched == 0:
        why = ("every est.log is empty" if unmatched == 0 else
               f"{swapped} of the {unmatched} estimates name a pair as 'j i' (gt.log lists 'i j': j maps into i)"
               if swapped else f"none of the {unmatched} estimates names a pair of this benchmark (the wrong one?)")
        _warn(warnings, f"no estimate in {edir} matched any of the {n_pairs} pairs of {bdir} ({why}): "
                        "every pair counts as a failure, RR 0 means nothing here")
    elif unmatched:
        _warn(warnings, f"{unmatched} estimates in {edir} match no pair of {bdir}"
                        + (f" ({swapped} of them with i and j swapped)" if swapped else "") + "; they are ignored")
    return {**score.to_dict(), "benchmark_dir": str(bdir), "estimate_dir": str(edir), "matched_pairs": matched,
            "unmatched_estimates": unmatched, "no_estimate_matched": matched == 0, "warnings": warnings}


def _shift(T: np.ndarray, offset: np.ndarray | None, back: bool) -> np.ndarray:
    """A transform between the original clouds and the clouds moved by ``-offset``: into the local
    frame (``back=False``), or back to the original coordinates (``back=True``)."""
    if offset is None:
        return T
    S = np.eye(4)
    S[:3, 3] = -offset
    Si = np.eye(4)
    Si[:3, 3] = offset
    return Si @ T @ S if back else S @ T @ Si


def _pair_clouds(cfg: DictConfig, warnings: list[str], flags: dict[str, Any]):
    """Both clouds (float64 read, float32 out, moved to a local origin when far from it), with checks
    and warnings: (source path, target path, (src, src colors), (tgt, tgt colors), offset or None)."""
    from pcrcg.data.layout import read_cloud

    sp = _existing(_need(cfg, "source", "a point cloud file (.ply, .pcd, .npz, .pth)"), "source cloud")
    tp = _existing(_need(cfg, "target", "a point cloud file (.ply, .pcd, .npz, .pth)"), "target cloud")
    (src, scol), (tgt, tcol) = read_cloud(sp, dtype=np.float64), read_cloud(tp, dtype=np.float64)
    for path, pts in ((sp, src), (tp, tgt)):
        if len(pts) < MIN_POINTS:
            raise DataError(path, f"holds {len(pts)} point(s); a registration needs at least {MIN_POINTS} "
                                  "(RANSAC draws 3 correspondences)")
    few = [f"{p.name}: {len(x)}" for p, x in ((sp, src), (tp, tgt)) if len(x) < FEW_POINTS]
    flags["few_points"] = bool(few)
    if few:
        _warn(warnings, f"too few points for a meaningful registration ({', '.join(few)}; RANSAC draws 3 at a "
                        f"time, under {FEW_POINTS} points any transform fits): the result is not reliable")
    offset = None
    far = max(float(np.abs(src).max()), float(np.abs(tgt).max()))
    if far > FLOAT32_SAFE:
        offset = np.round(np.concatenate([src, tgt]).mean(0), 0)
        spacing = float(np.spacing(np.float32(far)))
        _warn(warnings, f"coordinates reach {far:.0f} m, where float32 (the model's and RANSAC's precision) "
                        f"spaces values {spacing:.3g} m apart: both clouds are shifted by {(-offset).tolist()} to a "
                        "local origin, and the transform is given back in the original coordinates")
        src, tgt = src - offset, tgt - offset
    flags["origin_shift"] = None if offset is None else offset.tolist()
    extents = [float(np.linalg.norm(x.max(0) - x.min(0))) for x in (src, tgt)]
    odd = [f"{p.name}: {e:.3g} m" for p, e in zip((sp, tp), extents) if not SCALE_RANGE[0] <= e <= SCALE_RANGE[1]]
    flags["scale_suspect"] = bool(odd)
    if odd:
        _warn(warnings, f"cloud extent far from a scan in metres ({', '.join(odd)}; expected "
                        f"{SCALE_RANGE[0]}-{SCALE_RANGE[1]:.0f} m): voxel sizes and distances are in metres, so the "
                        "result is likely meaningless (units km or mm? scale the clouds to metres)")
    return sp, tp, (src.astype(np.float32), scol), (tgt.astype(np.float32), tcol), offset


def _load_views(prefixes: list[str], intrinsics: str | None) -> list:
    from pcrcg.data.dataset import View
    from pcrcg.data.layout import frame_paths, read_color, read_depth, read_intrinsics, read_pose
    from pcrcg.geometry import invert

    if not prefixes:
        return []
    K = read_intrinsics(_existing(intrinsics, "intrinsics file")) if intrinsics else None
    if K is None:
        raise ConfigError("intrinsics", intrinsics, "camera-intrinsics.txt of the views (sift_dlt)")
    paths = [frame_paths(Path(p)) for p in prefixes]
    for c, d, po in paths:  # check everything before reading
        for f in (c, d, po):
            _existing(str(f), "frame file")
    first = read_pose(paths[0][2])
    to_frag = invert(first)
    views = []
    for (c, d, po), prefix in zip(paths, prefixes):
        color, depth = read_color(c), read_depth(d)
        if color.shape[:2] != depth.shape:
            raise DataError(d, f"depth is {depth.shape[1]}x{depth.shape[0]} but color is {color.shape[1]}x{color.shape[0]}")
        views.append(View(color, depth, K.copy(), to_frag @ read_pose(po), -1, str(c)))
    return views


def run_pair_learned(cfg: DictConfig) -> dict[str, Any]:
    """Register two clouds with a trained checkpoint: network outputs, sampling, matching, RANSAC."""
    from pcrcg.evaluation.model import as_fragment
    from pcrcg.evaluation.stage import configs_from
    from pcrcg.models.train import infer_clouds, load_module
    from pcrcg.registration.feature_registration import register_features

    n_points = int(cfg.pair_points)
    if n_points < 3:
        raise ConfigError("pair_points", n_points, "an integer >= 3")
    ckpt = _existing(_need(cfg, "checkpoint", "a trained model's checkpoint (method=learned)"), "checkpoint")
    warnings: list[str] = []
    flags: dict[str, Any] = {}
    _, _, (src, _), (tgt, _), offset = _pair_clouds(cfg, warnings, flags)
    rcfg, _ = configs_from(cfg)
    module = load_module(ckpt, device=None if str(rcfg.device) == "auto" else rcfg.device)
    src_views = tgt_views = []
    if module.lifter is not None:
        src_views = _load_views(list(cfg.source_views or []), cfg.intrinsics)
        tgt_views = _load_views(list(cfg.target_views or []), cfg.intrinsics)
        need = int(module.lifter.cfg.n_views_needed)
        if len(src_views) < need or len(tgt_views) < need:
            raise ConfigError("source_views/target_views", [list(cfg.source_views), list(cfg.target_views)],
                              f"{need} frame prefixes .../frame-XXXXXX per fragment (this checkpoint lifts color "
                              f"from {need} view(s))")
        if offset is not None:  # the views' poses are camera-to-fragment: move them with the clouds
            S = np.eye(4)
            S[:3, 3] = -offset
            src_views = [v.transformed(S) for v in src_views]
            tgt_views = [v.transformed(S) for v in tgt_views]
    t0 = time.perf_counter()
    out = infer_clouds(module, src, tgt, src_views, tgt_views)
    res = register_features(as_fragment(out.src), as_fragment(out.tgt), n_points, rcfg, seed=int(cfg.seed))
    T = np.asarray(res.transform, dtype=float)
    own = {}
    if out.correspondences is not None:  # a model registered by RANSAC on its own correspondences (CoFiNet)
        from pcrcg.registration.correspondences import register_correspondences

        creg = register_correspondences(out.correspondences, out.correspondence_scores, n_points, rcfg,
                                        seed=int(cfg.seed))
        own = {"registration": "correspondences", "model_correspondences": int(len(out.correspondences)),
               "correspondences": int(len(creg.used)),  # what RANSAC saw (replaces the descriptor path's figures)
               "ransac_inliers": int(creg.ransac.n_inliers) if creg.ransac is not None else 0,
               "fitness": _num(creg.ransac.fitness) if creg.ransac is not None else None,
               "transform_features": _shift(T, offset, back=True).round(10).tolist()}
        T = np.asarray(creg.transform, dtype=float)
    if out.estimate is not None:  # a model that registers the pair itself (GeoTransformer's LGR): its estimate
        own = {"registration": "lgr", "lgr_pairs": int(len(out.estimate_pairs)),
               "transform_ransac": _shift(T, offset, back=True).round(10).tolist()}
        T = np.asarray(out.estimate, dtype=float)
    return {
        "method": "learned",
        "checkpoint": str(ckpt),
        "source": str(cfg.source),
        "target": str(cfg.target),
        "points": [len(out.src.points), len(out.tgt.points)],
        "n_points": n_points,
        "correspondences": int(len(res.correspondences)),
        "ransac_inliers": int(res.ransac.n_inliers),
        "fitness": _num(res.ransac.fitness),
        "color_coverage": _num(out.color_coverage),
        "seconds": round(time.perf_counter() - t0, 4),
        **flags,
        "warnings": warnings,
        **own,
        "transform": _shift(T, offset, back=True).round(10).tolist(),
    }


def run_pair(cfg: DictConfig) -> dict[str, Any]:
    from pcrcg.data.layout import check_rigid, read_matrix
    from pcrcg.evaluation.stage import configs_from
    from pcrcg.registration.baselines import METHODS, register_pair

    method = str(cfg.method)
    if method == "learned":
        return run_pair_learned(cfg)
    if method not in METHODS:
        raise ConfigError("method", method, " | ".join((*METHODS, "learned")))
    src = tgt = src_col = tgt_col = offset = None
    src_views = tgt_views = []
    warnings: list[str] = []
    flags: dict[str, Any] = {}
    if method in ("sift_dlt", "sift_lifted"):
        src_views = _load_views(list(cfg.source_views or []), cfg.intrinsics)
        tgt_views = _load_views(list(cfg.target_views or []), cfg.intrinsics)
        if not src_views or not tgt_views:
            raise ConfigError("source_views/target_views", [list(cfg.source_views), list(cfg.target_views)],
                              f"frame prefixes .../frame-XXXXXX of both fragments ({method} uses images)")
    else:
        sp, tp, (src, src_col), (tgt, tgt_col), offset = _pair_clouds(cfg, warnings, flags)
        if method == "color_icp":
            for path, col in ((sp, src_col), (tp, tgt_col)):
                if col is None:
                    raise DataError(path, "has no colors (method=color_icp needs them)")
    init = None
    if cfg.init is not None:
        ip = _existing(str(cfg.init), "initial transform file")
        init = _shift(check_rigid(read_matrix(ip, (4, 4)), ip), offset, back=False)
    _, bcfg = configs_from(cfg)
    t0 = time.perf_counter()
    res = register_pair(method, src, tgt, src_colors=src_col, tgt_colors=tgt_col, src_views=src_views,
                        tgt_views=tgt_views, init=init, cfg=bcfg, seed=int(cfg.seed))
    return {
        "method": method,
        "source": None if cfg.source is None else str(cfg.source),
        "target": None if cfg.target is None else str(cfg.target),
        "fitness": _num(res.fitness),
        "inlier_rmse": _num(res.inlier_rmse),
        "seconds": round(time.perf_counter() - t0, 4),
        **flags,
        "warnings": warnings,
        "transform": _shift(np.asarray(res.transform, dtype=float), offset, back=True).round(10).tolist(),
    }


def _num(v: float) -> float | None:
    return None if v is None or not np.isfinite(v) else float(v)


def _load_checkpoint(path: Path):
    """The trained module (CPU, eval mode); a file that is not a checkpoint of ``pcrcg.run`` is a DataError."""
    from pcrcg.models.train import load_module

    try:
        return load_module(path, device="cpu")
    except PcrcgError:
        raise
    except Exception as exc:  # noqa: BLE001 - torch/pickle/Lightning errors: reported with the file, on one line
        msg = " ".join(str(exc).split())[:200]
        raise DataError(path, f"is not a checkpoint of `python -m pcrcg.run` ({exc.__class__.__name__}: {msg})") from None


def learned_table(summary: dict[str, Any], n_points: list[int]) -> str:
    """RR / FMR / IR (%), RRE (deg), RTE (m) per benchmark and N, as printed by mode=benchmark method=learned."""
    lines = []
    for b, m in summary["benchmarks"].items():
        lines.append(f"{b}: {int(m.get('n_pairs', 0))} pairs, {int(m.get('n_counted', 0))} counted in RR")
        lines.append(f"  {'N':>5} {'RR':>6} {'FMR':>6} {'IR':>6} {'RRE':>6} {'RTE':>6}")
        own = [k for k in OWN_ESTIMATES if f"rr_{k}" in m]  # the model's own registration (GeoTransformer)
        for n in [*n_points, *own]:
            v = [m.get(f"{k}_{n}", float("nan")) for k in ("rr", "fmr", "ir", "rre", "rte")]
            v = [float("nan") if x is None else x for x in v]
            lines.append(f"  {n:>5} {v[0]:6.1f} {v[1]:6.1f} {v[2]:6.1f} {v[3]:6.2f} {v[4]:6.3f}")
    return "\n".join(lines)


def run_benchmark(cfg: DictConfig) -> dict[str, Any]:
    from pcrcg.evaluation.stage import CLASSICAL, configs_from, run_benchmark_mode

    method = str(cfg.method)
    if method != "learned" and method not in CLASSICAL:
        raise ConfigError("method", method, " | ".join((*CLASSICAL, "learned")))
    root = OmegaConf.select(cfg, "data.root")
    if root is None:
        raise ConfigError("data.root", None, "a data set folder in the 3DMatch layout (data.root=DIR or data=<name>)")
    _existing(str(root), "data root (data.root)", folder=True)
    ckpt, learned_views = None, 0
    if method == "learned":
        ckpt = _existing(_need(cfg, "checkpoint", "a trained model's checkpoint (method=learned)"), "checkpoint")
        module = _load_checkpoint(ckpt)
        learned_views = int(module.lifter.cfg.n_views_needed) if module.lifter is not None else 0
        del module
    rcfg, bcfg = configs_from(cfg)
    summary = run_benchmark_mode(
        method, str(root), str(cfg.out_dir), list(cfg.benchmarks), rcfg=rcfg, bcfg=bcfg,
        checkpoint=ckpt, learned_views=learned_views,
        init_dir=cfg.init_dir, n_views=int(cfg.views), seed=int(cfg.seed),
        max_pairs=None if cfg.max_pairs is None else int(cfg.max_pairs),
        thresholds=OmegaConf.to_container(cfg.eval, resolve=True), predator_variant=bool(cfg.predator_variant),
    )
    out = {"method": summary["method"], "out_dir": str(cfg.out_dir), "metrics": str(Path(str(cfg.out_dir)) / "metrics.json")}
    if method == "learned":
        print(learned_table(summary, list(rcfg.n_points)))
        keys = [f"{k}_{n}" for n in (*rcfg.n_points, *OWN_ESTIMATES) for k in ("rr", "fmr", "ir")]
        keys += ["rre_lgr", "rte_lgr", "rre", "rte", "n_pairs", "n_counted"]
        out["checkpoint"] = str(ckpt)
        # NaN (e.g. RRE without a registered pair) as null: the last line stays strict JSON
        out["benchmarks"] = {b: {k: _num(v[k]) for k in keys if k in v} for b, v in summary["benchmarks"].items()}
        if "color_coverage" in summary["metrics"]:
            out["color_coverage"] = _num(summary["metrics"]["color_coverage"])
        return out
    out["benchmarks"] = {b: {k: v[k] for k in ("rr", "rr_pair", "rre", "rte", "n_counted", "n_success") if k in v}
                         for b, v in summary["benchmarks"].items()}
    return out


def run(cfg: DictConfig) -> dict[str, Any]:
    """Dispatch on ``cfg.mode``; returns the JSON-ready result."""
    mode = str(cfg.mode)
    if mode == "score":
        return run_score(cfg)
    if mode == "pair":
        return run_pair(cfg)
    if mode == "benchmark":
        return run_benchmark(cfg)
    if mode == "tracked":
        from pcrcg.evaluation.tracked import run_tracked

        return run_tracked(cfg)
    raise ConfigError("mode", mode, " | ".join(MODES))


@hydra.main(version_base="1.3", config_path="../conf", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    from pcrcg.cli import one_line_errors

    keep_freed_memory()  # large tensors reuse the heap, as in a run (pcrcg.device)
    # the profile's threads (torch's and the native pools'), as a run's stages use them (the same speed)
    with one_line_errors("pcrcg.evaluate"), cpu_threads(OmegaConf.select(cfg, "profile.train.num_threads")):
        result = run(cfg)  # bad input: one line naming the file or setting, exit 2
    from pcrcg.cli import strict_json

    print(strict_json(result))  # NaN as null: the last line is strict JSON
    if result.get("failed"):  # mode=tracked: a run whose evaluation failed (the others were done)
        sys.exit(1)


if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.evaluate"):
        main()
