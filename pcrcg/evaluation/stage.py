"""The evaluation stage: running a method over the test benchmarks of a data set in the 3DMatch layout.

* :func:`run_classical` registers every pair of one benchmark with ``fpfh | icp | color_icp |
  sift_dlt | sift_lifted``, writes ``<out_dir>/<scene>/est.log`` and scores it;
* :func:`evaluate_learned` evaluates a trained checkpoint on one benchmark at every N;
* :func:`evaluate` is the pipeline's evaluation stage (``stages.evaluate`` of ``conf/run.yaml``
  calls it through ``pcrcg.pipeline.evaluate_method``): the learned model at every N, or a
  classical method (ICP / colored ICP optionally started from the learned model's estimates), on
  every benchmark of ``eval.benchmarks``; metrics named ``<benchmark>/<metric>[_<N>]``;
* :func:`run_benchmark_mode` is ``python -m pcrcg.evaluate mode=benchmark``: any method, learned
  included, over the test benchmarks of any data set in the layout.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
from tqdm import tqdm

from pcrcg.cli import strict_json
from pcrcg.data.layout import BENCHMARKS, Layout, evenly
from pcrcg.device import resolve_device
from pcrcg.errors import ConfigError, DataError
from pcrcg.evaluation.metrics import (
    FMR_THRESHOLD,
    INLIER_DISTANCE,
    RMSE_THRESHOLD,
    SceneGT,
    correspondence_metrics,
    inlier_ratio,
    load_benchmark,
    load_estimates,
    score_benchmark,
    write_estimates,
)
from pcrcg.evaluation.model import evaluate_model_outputs, subset
from pcrcg.evaluation.pairs import pair_artifacts
from pcrcg.registration.baselines import METHODS as CLASSICAL, SIFT_METHODS, BaselineConfig, register_pair
from pcrcg.registration.feature_registration import RegistrationConfig

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- configs


def _plain(node: Any) -> Any:
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(node, (DictConfig, ListConfig)):
            return OmegaConf.to_container(node, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    return node


def _select(cfg: Any, dotted: str, default: Any = None) -> Any:
    cur = cfg
    for part in dotted.split("."):
        if cur is None:
            return default
        try:
            cur = cur.get(part) if hasattr(cur, "get") else getattr(cur, part, None)
        except Exception:  # noqa: BLE001 - missing/interpolation errors mean "not set"
            return default
    return default if cur is None else cur


def configs_from(cfg: Any, device: str | None = None) -> tuple[RegistrationConfig, BaselineConfig]:
    """Registration and baseline settings from a composed config.

    Reads the ``registration`` node when present (``conf/registration/default.yaml``). In the run
    config its ``n_points``, ``ransac.max_iterations`` and ``ransac.distance`` follow ``eval.n_points``,
    ``eval.ransac_iterations`` and ``eval.ransac_distance`` (one setting each, :mod:`pcrcg.mirrors`):
    a node without them takes the ``eval`` value, and two values that differ are a
    :class:`~pcrcg.errors.ConfigError` naming both keys (nothing is silently overwritten).
    """
    from pcrcg.mirrors import check_mirrors

    reg = dict(_plain(_select(cfg, "registration", {})) or {})
    ev = dict(_plain(_select(cfg, "eval", {})) or {})
    ransac = dict(reg.get("ransac") or {})
    for ev_key, node, key in (("n_points", reg, "n_points"), ("ransac_iterations", ransac, "max_iterations"),
                              ("ransac_distance", ransac, "distance")):
        if node.get(key) is None and ev.get(ev_key) is not None:
            node[key] = ev[ev_key]
    reg["ransac"] = ransac
    check_mirrors({"eval": ev, "registration": reg})
    if device is not None and str(device) != "auto":
        reg["device"] = str(device)
    if str(reg.get("device", "cpu")) == "auto":
        reg["device"] = resolve_device("auto")
    rcfg = RegistrationConfig.from_dict(reg)
    bcfg = BaselineConfig.from_dict({**reg, "ransac": dataclasses.asdict(rcfg.ransac), "device": rcfg.device})
    return rcfg, bcfg


def thresholds_from(cfg: Any) -> dict[str, float]:
    ev = _select(cfg, "eval", {}) or {}
    return {
        "inlier_distance": float(_select(ev, "inlier_distance", INLIER_DISTANCE)),
        "fmr_threshold": float(_select(ev, "fmr_threshold", FMR_THRESHOLD)),
        "rmse_threshold": float(_select(ev, "rmse_threshold", RMSE_THRESHOLD)),
    }


# --------------------------------------------------------------------------- classical methods


def check_layout(root: str | os.PathLike, benchmarks: Iterable[str]) -> dict[str, dict[str, SceneGT]]:
    """Check the benchmark files and fragment folders of a data set before work starts."""
    layout = Layout(root)
    if not layout.root.is_dir():
        raise DataError(layout.root, "data root does not exist (run `python -m pcrcg.prepare` or set data.root)")
    out = {}
    for b in benchmarks:
        if b not in BENCHMARKS:
            raise ConfigError("benchmarks", b, " | ".join(BENCHMARKS))
        gt = load_benchmark(layout.benchmark_dir(b))
        for s, g in gt.items():
            for p in g.pairs:
                for f in (p.i, p.j):
                    path = layout.fragment(s, f)
                    if not path.is_file():
                        raise DataError(path, f"fragment of pair {p.i} {p.j} of {b}/{s} is missing")
        out[b] = gt
    return out


def run_classical(
    method: str,
    root: str | os.PathLike,
    benchmark: str,
    *,
    cfg: BaselineConfig | None = None,
    out_dir: str | os.PathLike | None = None,
    init: Mapping[str, Mapping[tuple[int, int], np.ndarray]] | None = None,
    n_views: int = 2,
    seed: int = 0,
    max_pairs: int | None = None,
    gt: Mapping[str, SceneGT] | None = None,
    thresholds: Mapping[str, float] | None = None,
    predator_variant: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    """Register every pair of ``benchmark`` with a classical method and score it.

    ``predator_variant``: the recall also leaves out the first pair of each scene, as Predator's
    script does (the same setting the learned rows get). ``init`` ({scene: {(i, j): 4x4}}) starts ICP / colored ICP from given estimates (identity
    where a pair has none). Returns ``{"score": BenchmarkScore, "metrics": {...}, "estimates":
    {scene: {(i, j): 4x4}}, "seconds_per_pair": float}``; ``out_dir/<scene>/est.log`` when given.
    """
    from pcrcg.data.dataset import PairDataset

    if method not in CLASSICAL:
        raise ConfigError("method", method, " | ".join(CLASSICAL))
    cfg = cfg or BaselineConfig()
    th = {**thresholds_from({}), **dict(thresholds or {})}
    layout = Layout(root)
    gt = gt if gt is not None else load_benchmark(layout.benchmark_dir(benchmark))
    ds = PairDataset(root, benchmark, n_views=n_views if method in SIFT_METHODS else 0)
    keys = [(p.scene, p.i, p.j) for p in ds.pairs if p.scene in gt]
    if max_pairs is not None:  # spread over the benchmark (the first n would be one or two scenes)
        keys = evenly(keys, int(max_pairs))
    index = {(p.scene, p.i, p.j): k for k, p in enumerate(ds.pairs)}
    estimates: dict[str, dict[tuple[int, int], np.ndarray]] = defaultdict(dict)
    irs: dict[str, list[float]] = defaultdict(list)
    n_no_init = 0
    t0 = time.perf_counter()
    for scene, i, j in tqdm(keys, desc=f"{method} {benchmark}", unit="pair", disable=not progress):
        sample = ds[index[(scene, i, j)]]
        T0 = None
        if init is not None and method in ("icp", "color_icp"):
            T0 = init.get(scene, {}).get((i, j))
            n_no_init += T0 is None
        res = register_pair(
            method, sample.src_points, sample.tgt_points,
            src_colors=sample.src_colors, tgt_colors=sample.tgt_colors,
            src_views=sample.src_views, tgt_views=sample.tgt_views, init=T0, cfg=cfg, seed=seed,
        )
        estimates[scene][(i, j)] = res.transform
        if res.src_corr is not None:
            irs[scene].append(inlier_ratio(res.src_corr, res.tgt_corr, sample.transform, th["inlier_distance"])
                              if len(res.src_corr) else 0.0)
    seconds = (time.perf_counter() - t0) / max(len(keys), 1)
    if n_no_init:
        log.warning("%d pairs had no initial estimate and started from the identity", n_no_init)
    evaluated: dict[str, set] = defaultdict(set)
    for s, i, j in keys:
        evaluated[s].add((i, j))
    scored = subset(gt, evaluated) if max_pairs is not None else dict(gt)
    score = score_benchmark(scored, estimates, predator_variant, threshold=th["rmse_threshold"])
    metrics = {"rr": score.rr, "rr_pair": score.rr_pair, "rre": score.rre, "rte": score.rte,
               "seconds_per_pair": seconds}
    if irs:
        cm = correspondence_metrics({s: irs.get(s, []) for s in scored}, th["fmr_threshold"])
        metrics.update({"fmr": cm["fmr"], "ir": cm["ir"], "fmr_pair": cm["fmr_pair"]})
    if out_dir is not None:
        for s, g in gt.items():
            write_estimates(Path(out_dir) / s / "est.log", g, estimates.get(s, {}))
    return {"score": score, "metrics": metrics, "estimates": dict(estimates), "seconds_per_pair": seconds}


# --------------------------------------------------------------------------- learned model


def predict_outputs(cfg: Any, data_root: str | os.PathLike, checkpoint: str | os.PathLike | None, benchmark: str,
                    device: str = "cpu", max_pairs: int | None = None, progress: bool = True) -> Iterable[Any]:
    """Per-pair network outputs (objects with ``scene, i, j, src, tgt[, color_coverage]``) from the
    model stage's hook ``pcrcg.models.predict.predict_benchmark``."""
    if checkpoint is None or not Path(checkpoint).is_file():
        raise DataError(checkpoint, "checkpoint of the learned model is missing (method=learned needs one)")
    from pcrcg.models.predict import predict_benchmark

    it = predict_benchmark(cfg, data_root=data_root, checkpoint=checkpoint, benchmark=benchmark, device=device,
                           max_pairs=max_pairs, progress=progress)
    for k, out in enumerate(it):
        if max_pairs is not None and k >= max_pairs:
            break
        yield out


def evaluate_learned(cfg: Any, data_root: str | os.PathLike, checkpoint: str | os.PathLike | None, benchmark: str,
                     gt: Mapping[str, SceneGT], *, rcfg: RegistrationConfig, est_dir: str | os.PathLike | None,
                     seed: int = 0, max_pairs: int | None = None, predator_variant: bool = False,
                     thresholds: Mapping[str, float] | None = None, progress: bool = True) -> dict[str, float]:
    """A trained checkpoint on one benchmark at every N of ``rcfg.n_points``: the network's outputs
    (:func:`predict_outputs`) registered and scored by :func:`evaluate_model_outputs` (``rr_<N>``,
    ``fmr_<N>``, ``ir_<N>``, ``rre_<N>``, ``rte_<N>``, ``rre``, ``rte``, ``color_coverage``, pair
    counts); ``<est_dir>/<N>/<scene>/est.log`` when ``est_dir`` is given."""
    th = {**thresholds_from({}), **dict(thresholds or {})}
    outputs = predict_outputs(cfg, data_root, checkpoint, benchmark, rcfg.device, max_pairs, progress)
    return evaluate_model_outputs(outputs, gt, cfg=rcfg, est_dir=est_dir, seed=seed, predator_variant=predator_variant,
                                  only_evaluated=max_pairs is not None, progress=progress, **th)


def check_views(root: str | os.PathLike, gts: Mapping[str, Mapping[str, SceneGT]], n_views: int) -> None:
    """Before work: every fragment of the benchmarks ``gts`` ({benchmark: {scene: SceneGT}}) has its
    ``.info.txt`` and the files of its first ``n_views`` views (first, last, middle frame)."""
    from pcrcg.data.dataset import view_frame_ids
    from pcrcg.data.layout import frame_paths, read_fragment_info

    if n_views <= 0:
        return
    layout = Layout(root)
    seen: set[tuple[str, int]] = set()
    for gt in gts.values():
        for s, g in gt.items():
            if not layout.intrinsics(s).is_file():
                raise DataError(layout.intrinsics(s), f"is missing (the model lifts color from {n_views} view(s) "
                                                      "of each fragment)")
            for f in sorted({k for p in g.pairs for k in (p.i, p.j)}):
                if (s, f) in seen:
                    continue
                seen.add((s, f))
                info_path = layout.fragment_info(s, f)
                if not info_path.is_file():
                    raise DataError(info_path, f"is missing: the model lifts color from {n_views} view(s) of each "
                                               "fragment, named by its .info.txt")
                info = read_fragment_info(info_path)
                for fid in view_frame_ids(info, n_views):
                    for path in frame_paths(layout.frame_prefix(s, info.seq, fid)):
                        if not path.is_file():
                            raise DataError(path, f"view of fragment {f} of {s} is missing")


# --------------------------------------------------------------------------- the pipeline's stage


def _protocol(rcfg: RegistrationConfig, gt: Mapping[str, SceneGT], th: Mapping[str, float], seed: int,
              predator_variant: bool) -> dict[str, Any]:
    from pcrcg.evaluation.metrics import counted_mask

    return {
        "pairs": sum(len(g.pairs) for g in gt.values()),
        "pairs_counted_in_rr": int(sum(counted_mask(g.pairs, predator_variant).sum() for g in gt.values())),
        "scenes": len(gt),
        "recall": "per scene, then mean over scenes; j - i > 1 only",
        "predator_variant": predator_variant,
        "sampling": rcfg.sampling,
        "fewer_points": rcfg.fewer_points,
        "mutual": rcfg.mutual,
        "ransac": {"backend": rcfg.backend, **dataclasses.asdict(rcfg.ransac)},
        "ransac_budget": rcfg.ransac.budget,
        "thresholds": dict(th),
        "seed": seed,
    }


def evaluate(cfg: Any, *, data_root: str | os.PathLike, checkpoint: str | os.PathLike | None = None,
             out_dir: str | os.PathLike, device: str | None = None, progress: bool = True) -> dict[str, Any]:
    """The evaluation stage of ``python -m pcrcg.run``.

    Returns ``{"metrics": {"<benchmark>/<name>": value}, "artifacts": [(path, folder)],
    "protocol": {...}}``. ``method=learned``: ``<b>/rr_<N>``, ``fmr_<N>``, ``ir_<N>``,
    ``rre_<N>``, ``rte_<N>``, ``<b>/rre``, ``<b>/rte`` (at the largest N), ``<b>/color_coverage`` and ``color_coverage``
    (the mean of the benchmarks');
    classical methods: ``<b>/rr``, ``<b>/rre``, ``<b>/rte`` (+ ``fmr``, ``ir`` for fpfh and the SIFT methods).
    ``icp_init=learned`` starts ICP from the learned model's estimates at the largest N.
    """
    method = str(_select(cfg, "method", "learned"))
    seed = int(_select(cfg, "seed", 0))
    benchmarks = list(_plain(_select(cfg, "eval.benchmarks", list(BENCHMARKS))))
    max_pairs = _select(cfg, "eval.max_pairs", None)
    max_pairs = int(max_pairs) if max_pairs is not None else None
    predator_variant = bool(_select(cfg, "eval.predator_variant", False))
    if method != "learned" and method not in CLASSICAL:
        raise ConfigError("method", method, "learned | " + " | ".join(CLASSICAL))
    from_learned = method == "learned" or (method in ("icp", "color_icp") and _select(cfg, "icp_init") == "learned")
    rcfg, bcfg = configs_from(cfg, device)
    if method != "learned":  # ICP starts from the learned estimates at the largest N only
        rcfg = dataclasses.replace(rcfg, n_points=(max(rcfg.n_points),))
    th = thresholds_from(cfg)
    out_dir = Path(out_dir)
    gts = check_layout(data_root, benchmarks)
    metrics: dict[str, float] = {}
    artifacts: list[tuple[Path, str]] = []
    protocol: dict[str, Any] = {"method": method}
    coverage: list[float] = []
    for b in benchmarks:
        gt = gts[b]
        protocol[b] = _protocol(rcfg, gt, th, seed, predator_variant)
        if from_learned:
            est_dir = out_dir / "learned" / b
            m = evaluate_learned(cfg, data_root, checkpoint, b, gt, rcfg=rcfg, est_dir=est_dir, seed=seed,
                                 max_pairs=max_pairs, predator_variant=predator_variant, thresholds=th,
                                 progress=progress)
            if method == "learned":
                for k, v in m.items():
                    if k == "color_coverage":  # per benchmark, and pooled (the mean of the benchmarks') below
                        coverage.append(v)
                    metrics[f"{b}/{k}"] = v
                artifacts.append((est_dir, f"estimates/{b}"))
                continue
            init_dir = est_dir / str(max(rcfg.n_points))
            init, _ = load_estimates(init_dir, gt.keys())
        else:
            init = None
        est_dir = out_dir / method / b
        res = run_classical(method, data_root, b, cfg=bcfg, out_dir=est_dir, init=init,
                            n_views=int(_select(cfg, "views", 2) or 2), seed=seed, max_pairs=max_pairs, gt=gt,
                            thresholds=th, predator_variant=predator_variant, progress=progress)
        for k, v in res["metrics"].items():
            metrics[f"{b}/{k}"] = v
        artifacts.append((est_dir, f"estimates/{b}"))
    if coverage:
        metrics["color_coverage"] = float(np.mean(coverage))
    artifacts += pair_artifacts(out_dir, gts, artifacts, predator_variant, th, only_present=max_pairs is not None)
    out_dir.mkdir(parents=True, exist_ok=True)
    mfile = out_dir / "metrics.json"
    mfile.write_text(strict_json({"metrics": metrics, "protocol": protocol}, indent=1))  # NaN as null
    artifacts.append((mfile, "evaluation"))
    return {"metrics": metrics, "artifacts": artifacts, "protocol": protocol}


def run_benchmark_mode(
    method: str,
    data_root: str | os.PathLike,
    out_dir: str | os.PathLike,
    benchmarks: Iterable[str],
    *,
    rcfg: RegistrationConfig,
    bcfg: BaselineConfig,
    checkpoint: str | os.PathLike | None = None,
    learned_views: int = 0,
    init_dir: str | os.PathLike | None = None,
    n_views: int = 2,
    seed: int = 0,
    max_pairs: int | None = None,
    thresholds: Mapping[str, float] | None = None,
    predator_variant: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    """``python -m pcrcg.evaluate mode=benchmark``: a method over every benchmark of a data set.

    Classical methods write ``<out_dir>/<benchmark>/<scene>/est.log``; ``init_dir`` (ICP) holds
    ``<benchmark>/<scene>/est.log`` estimates to start from. ``method=learned`` evaluates
    ``checkpoint`` as the pipeline does (:func:`evaluate_learned`: every N of ``rcfg.n_points``,
    ``<out_dir>/<benchmark>/<N>/<scene>/est.log``); a model that lifts color reads
    ``learned_views`` views of each fragment, checked before work. Returns (and writes as
    ``<out_dir>/metrics.json``) ``{"method", "data_root", "benchmarks": {b: {...}}, "metrics":
    {"<benchmark>/<name>": value}}``, the metrics named as a run logs them.
    """
    benchmarks = list(benchmarks)
    if method == "learned":
        if checkpoint is None or not Path(checkpoint).is_file():
            raise DataError(checkpoint, "checkpoint of the learned model is missing (method=learned needs one)")
    elif method not in CLASSICAL:
        raise ConfigError("method", method, "learned | " + " | ".join(CLASSICAL))
    th = {**thresholds_from({}), **dict(thresholds or {})}
    gts = check_layout(data_root, benchmarks)
    if method == "learned":
        check_views(data_root, gts, learned_views)
    inits = {}
    if init_dir is not None:
        for b in benchmarks:
            d = Path(init_dir) / b
            if not d.is_dir():
                raise DataError(d, "folder of initial estimates (<benchmark>/<scene>/est.log) is missing")
            inits[b], _ = load_estimates(d, gts[b].keys())
    out_dir = Path(out_dir)
    summary: dict[str, Any] = {"method": method, "data_root": str(data_root), "benchmarks": {}, "metrics": {}}
    if method == "learned":
        summary["checkpoint"] = str(checkpoint)
    coverage: list[float] = []
    for b in benchmarks:
        if method == "learned":
            entry: dict[str, Any] = evaluate_learned(
                None, data_root, checkpoint, b, gts[b], rcfg=rcfg, est_dir=out_dir / b, seed=seed, max_pairs=max_pairs,
                predator_variant=predator_variant, thresholds=th, progress=progress)
            if "color_coverage" in entry:
                coverage.append(entry["color_coverage"])  # kept per benchmark too
        else:
            res = run_classical(method, data_root, b, cfg=bcfg, out_dir=out_dir / b, init=inits.get(b),
                                n_views=n_views, seed=seed, max_pairs=max_pairs, gt=gts[b], thresholds=th,
                                predator_variant=predator_variant, progress=progress)
            entry = res["score"].to_dict()
            entry.update({k: v for k, v in res["metrics"].items() if k not in entry})
        summary["metrics"].update({f"{b}/{k}": v for k, v in entry.items()
                                   if isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool)})
        entry["protocol"] = _protocol(rcfg, gts[b], th, seed, predator_variant)
        summary["benchmarks"][b] = entry
    if coverage:
        summary["metrics"]["color_coverage"] = float(np.mean(coverage))
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "metrics.json").write_text(strict_json(summary, indent=1))  # NaN as null
    return summary
