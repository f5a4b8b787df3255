"""Evaluating a learned model's per-point outputs with Predator's protocol at every N."""

from __future__ import annotations

import logging
import os
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
from tqdm import tqdm

from pcrcg.device import torch_threads
from pcrcg.evaluation.metrics import (
    FMR_THRESHOLD,
    INLIER_DISTANCE,
    RMSE_THRESHOLD,
    SceneGT,
    correspondence_metrics,
    inlier_ratio,
    load_benchmark,
    score_benchmark,
    write_estimates,
)
from pcrcg.evaluation.pairs import INLIER_RATIO_FILE, write_inlier_ratios
from pcrcg.registration.correspondences import register_correspondences
from pcrcg.registration.feature_registration import FragmentOutput, RegistrationConfig, pair_seed, register_features
from pcrcg.registration.ransac import ransac

log = logging.getLogger(__name__)


def as_fragment(x: Any) -> FragmentOutput:
    """A :class:`FragmentOutput` as it is, or any mapping or object with ``points``, ``descriptors``,
    ``overlap``, ``matchability`` as one."""
    if isinstance(x, FragmentOutput):
        return x
    if isinstance(x, Mapping):
        return FragmentOutput(x["points"], x["descriptors"], x["overlap"], x["matchability"])
    return FragmentOutput(x.points, x.descriptors, x.overlap, x.matchability)


def subset(gt: Mapping[str, SceneGT], keys: Mapping[str, set[tuple[int, int]]]) -> dict[str, SceneGT]:
    """The ground truth restricted to the given pairs per scene (scenes without pairs dropped)."""
    out = {}
    for s, g in gt.items():
        ks = keys.get(s, set())
        sel = [k for k, p in enumerate(g.pairs) if (p.i, p.j) in ks]
        if sel:
            out[s] = SceneGT(s, tuple(g.pairs[k] for k in sel), g.transforms[sel], g.infos[sel])
    return out


def own_estimates(out: Any, T_gt: np.ndarray, cfg: RegistrationConfig, seed: np.random.SeedSequence,
                  inlier_distance: float) -> dict[str, tuple[np.ndarray, float]]:
    """``{"lgr": (4x4, inlier ratio), "lgr_ransac": ...}`` for an output with ``estimate`` and
    ``estimate_pairs`` (C, 6) (source xyz, target xyz), else {}; RANSAC as ``cfg.ransac``."""
    T = getattr(out, "estimate", None)
    if T is None:
        return {}
    pairs = np.asarray(getattr(out, "estimate_pairs", None) if getattr(out, "estimate_pairs", None) is not None
                       else np.zeros((0, 6)), np.float32).reshape(-1, 6)
    ir = inlier_ratio(pairs[:, :3], pairs[:, 3:], T_gt, inlier_distance) if len(pairs) else 0.0
    res = {"lgr": (np.asarray(T, np.float64), ir)}
    if len(pairs) >= 3:
        idx = np.arange(len(pairs))
        with torch_threads(cfg.ransac.threads, cfg.device):
            r = ransac(pairs[:, :3], pairs[:, 3:], np.stack([idx, idx], 1), cfg.ransac, seed=np.random.default_rng(seed),
                       device=cfg.device)
        res["lgr_ransac"] = (np.asarray(r.transform, np.float64), ir)
    else:
        res["lgr_ransac"] = (np.eye(4), ir)
    return res


@dataclass
class _Estimates:
    """What the pairs gave, per key (an N of the protocol, or a model's own estimate): transforms
    ``est[key][scene][(i, j)]`` (4, 4), inlier ratios per scene in pair order and per pair, seconds."""

    keys: list[Any]
    est: dict[Any, dict[str, dict[tuple[int, int], np.ndarray]]] = field(default_factory=dict)
    irs: dict[Any, dict[str, list[float]]] = field(default_factory=dict)
    pair_irs: dict[Any, dict[str, dict[tuple[int, int], float]]] = field(default_factory=dict)
    seconds: dict[Any, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for key in self.keys:
            self._open(key)

    def _open(self, key: Any) -> None:
        self.est[key], self.irs[key], self.pair_irs[key] = defaultdict(dict), defaultdict(list), defaultdict(dict)
        self.seconds[key] = 0.0

    def record(self, key: Any, scene: str, ij: tuple[int, int], T: np.ndarray, ir: float) -> None:
        """One pair's estimate T (4, 4) and inlier ratio under ``key`` (a new key is added after the others)."""
        if key not in self.est:
            self.keys.append(key)
            self._open(key)
        self.est[key][scene][ij] = T
        self.irs[key][scene].append(ir)
        self.pair_irs[key][scene][ij] = ir


def _register_at(out: Any, src: FragmentOutput, tgt: FragmentOutput, n: int, T_gt: np.ndarray,
                 cfg: RegistrationConfig, seed: np.random.SeedSequence, inlier_distance: float) -> tuple[np.ndarray, float]:
    """One pair at one N: the transform (4, 4) and the inlier ratio of the correspondences it used. A model
    that gives its own correspondences (CoFiNet: ``out.correspondences`` (C, 6)) is registered by RANSAC on N
    of them; otherwise Predator's sampling, matching and RANSAC on the per-point outputs."""
    corr = getattr(out, "correspondences", None)
    if corr is not None:
        pts = np.asarray(corr, np.float32).reshape(-1, 6)
        creg = register_correspondences(pts, out.correspondence_scores, n, cfg, seed=seed)
        u = pts[creg.used]
        return creg.transform, (inlier_ratio(u[:, :3], u[:, 3:], T_gt, inlier_distance) if len(u) else 0.0)
    reg = register_features(src, tgt, n, cfg, seed=seed)
    c = reg.correspondences
    return reg.transform, (inlier_ratio(src.points[c[:, 0]], tgt.points[c[:, 1]], T_gt, inlier_distance) if len(c) else 0.0)


def _score(gt: Mapping[str, SceneGT], scored: Mapping[str, SceneGT], acc: _Estimates, n_done: int,
           est_dir: str | os.PathLike | None, predator_variant: bool, fmr_threshold: float,
           rmse_threshold: float) -> tuple[dict[str, float], Any]:
    """Per key: RR, FMR, IR, RRE, RTE and seconds per pair over the ``scored`` pairs (and est.log / inlier
    ratio files under ``est_dir/<key>/<scene>/`` for every pair of ``gt``); returns them and the last score."""
    metrics: dict[str, float] = {}
    score = None
    for n in acc.keys:
        score = score_benchmark(scored, acc.est[n], predator_variant, threshold=rmse_threshold)
        cm = correspondence_metrics({s: acc.irs[n].get(s, []) for s in scored}, fmr_threshold)
        metrics.update({
            f"rr_{n}": score.rr,
            f"rr_pair_{n}": score.rr_pair,
            f"fmr_{n}": cm["fmr"],
            f"fmr_pair_{n}": cm["fmr_pair"],
            f"ir_{n}": cm["ir"],
            f"rre_{n}": score.rre,
            f"rte_{n}": score.rte,
            f"seconds_per_pair_{n}": acc.seconds[n] / max(n_done, 1),
        })
        if est_dir is not None:
            for s, g in gt.items():
                write_estimates(Path(est_dir) / str(n) / s / "est.log", g, acc.est[n].get(s, {}))
                write_inlier_ratios(Path(est_dir) / str(n) / s / INLIER_RATIO_FILE, g, acc.pair_irs[n].get(s, {}))
    return metrics, score


def evaluate_model_outputs(
    outputs: Iterable[Any],
    benchmark: str | os.PathLike | Mapping[str, SceneGT],
    *,
    cfg: RegistrationConfig | None = None,
    est_dir: str | os.PathLike | None = None,
    seed: int = 0,
    predator_variant: bool = False,
    inlier_distance: float = INLIER_DISTANCE,
    fmr_threshold: float = FMR_THRESHOLD,
    rmse_threshold: float = RMSE_THRESHOLD,
    only_evaluated: bool = False,
    progress: bool = True,
) -> dict[str, float]:
    """Register every pair at every N of ``cfg.n_points`` and score it (see the package docstring)."""
    cfg = cfg or RegistrationConfig()
    gt = benchmark if isinstance(benchmark, Mapping) else load_benchmark(benchmark)
    lookup = {(s, p.i, p.j): (g, k) for s, g in gt.items() for k, p in enumerate(g.pairs)}
    ns = list(cfg.n_points)
    acc = _Estimates(list(ns))  # the model's own estimates (pairs.OWN_ESTIMATES), when it gives them, are added after
    seen: dict[str, set[tuple[int, int]]] = defaultdict(set)
    coverage: list[float] = []
    n_done = 0
    for out in tqdm(outputs, desc="registration", unit="pair", disable=not progress):
        scene, i, j = str(out.scene), int(out.i), int(out.j)
        if (scene, i, j) not in lookup:
            raise KeyError(f"pair {scene} {i} {j} is not in the benchmark's gt.log")
        if (i, j) in seen[scene]:
            raise KeyError(f"pair {scene} {i} {j} was given twice")
        seen[scene].add((i, j))
        g, k = lookup[(scene, i, j)]
        T_gt = g.transforms[k]
        src, tgt = as_fragment(out.src), as_fragment(out.tgt)
        cov = getattr(out, "color_coverage", float("nan"))
        if cov is not None and np.isfinite(cov):
            coverage.append(float(cov))
        for n in ns:
            t0 = time.perf_counter()
            T, ir = _register_at(out, src, tgt, n, T_gt, cfg, pair_seed(seed, scene, i, j, n), inlier_distance)
            acc.seconds[n] += time.perf_counter() - t0
            acc.record(n, scene, (i, j), T, ir)
        t0 = time.perf_counter()
        mine = own_estimates(out, T_gt, cfg, pair_seed(seed, scene, i, j, 0), inlier_distance)
        for key, (T_own, ir) in mine.items():
            acc.record(key, scene, (i, j), T_own, ir)
        if "lgr_ransac" in mine:  # LGR itself runs in the network's inference
            acc.seconds["lgr_ransac"] += time.perf_counter() - t0
        n_done += 1

    scored = subset(gt, seen) if only_evaluated else dict(gt)
    metrics, score = _score(gt, scored, acc, n_done, est_dir, predator_variant, fmr_threshold, rmse_threshold)
    top = max(ns)
    metrics["rre"] = metrics[f"rre_{top}"]
    metrics["rte"] = metrics[f"rte_{top}"]
    metrics["n_pairs"] = float(sum(len(g.pairs) for g in scored.values()))
    metrics["n_counted"] = float(score.n_counted)
    metrics["n_evaluated"] = float(n_done)
    if coverage:
        metrics["color_coverage"] = float(np.mean(coverage))
    return metrics
