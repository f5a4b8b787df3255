"""The 3DMatch / 3DLoMatch evaluation protocol (pure NumPy).

Per pair
--------
* **Inlier ratio** (IR): fraction of putative correspondences ``(x, y)`` whose residual
  ``||T_gt x - y||`` under the ground truth is below 10 cm (strictly).
* **Feature matching recall** (FMR): fraction of pairs with IR > 5 % (strictly).
* **Registration error** (the 3DMatch/Redwood approximation of the RMSE over the ground-truth
  correspondences): with ``dT = inv(T_gt) @ T_est`` and ``e = [t, q_xyz]`` (translation of
  ``dT`` and the vector part of its unit quaternion taken with ``w >= 0``),
  ``err = e^T info e / info[0, 0]`` where ``info`` is the pair's 6x6 matrix from ``gt.info``
  (translation first; ``info[0, 0]`` is the number of ground-truth correspondences).
  A pair is registered when ``err <= 0.2**2`` (``<=`` as in the official MATLAB code and every
  published port; ``<`` differs only on a set of measure zero).
* **RRE** ``arccos((tr(R_est^T R_gt) - 1) / 2)`` in degrees and **RTE** ``||t_est - t_gt||`` in
  metres.

Per benchmark
-------------
* Registration recall (RR) counts only pairs that are not adjacent (``j - i > 1``; the
  ``gt.log`` of both benchmarks lists every pair with ``i < j``): 1,279 of the 1,623 pairs of
  3DMatch and 1,726 of the 1,781 of 3DLoMatch. Recall is computed per scene and then averaged
  over scenes (``rr``); the pooled, pair-level recall is reported beside it (``rr_pair``).
* A pair without an estimate counts as a failure (a scene without ``est.log``: all its pairs).
* A pair whose information matrix is all zeros has the error 0/0 = NaN and always fails, as in
  every published implementation. The official 3DLoMatch files hold one such pair
  (``sun3d-home_md-home_md_scan9_2012_sep_30``, pair 23 25, non-adjacent), so even the ground
  truth scores 1,725 / 1,726 there.
* IR and FMR count every pair, adjacent ones included, and are also averaged per scene and then
  over scenes (as Predator's evaluation script does: "averaged twice").
* RRE / RTE: over the registered, counted pairs; per scene the median, then the mean over the
  scenes that registered at least one pair (Predator's "Mean median RRE/RTE"). The pooled mean
  over pairs is reported as ``rre_pair_mean`` / ``rte_pair_mean``.

Where published implementations differ (``predator_variant=True``)
-----------------------------------------------------------------
Predator's ``lib/benchmark.py`` (also used by PCR-CG) ports the MATLAB protocol to Python but
keeps the MATLAB habit of storing pair indices in a mask and testing ``mask > 0``::

    gt_mask[i, j] = idx          # idx = 0-based position of the pair in gt.log
    n_gt = np.sum(gt_mask > 0)   # ... and later: if gt_mask[i, j] > 0: count the pair

With 0-based indices the first pair listed in each scene's ``gt.log`` gets ``idx = 0`` and is
never counted, neither as a success nor in the denominator. In 3DMatch every scene starts with
an adjacent pair (``0 1`` or ``1 2``), which is excluded anyway, so nothing changes; in 3DLoMatch
the first pair of 7 of the 8 scenes is non-adjacent, and 1,719 instead of 1,726 pairs count. The same script also
averages the per-scene median RRE/RTE with a 0 for scenes that registered no pair. The flag
reproduces both behaviours so that numbers are comparable with papers that used that script;
the default follows the official protocol.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from pcrcg.data.layout import PairRecord, check_rigid, read_gt_info, read_gt_log, write_gt_log
from pcrcg.errors import DataError

log = logging.getLogger(__name__)

INLIER_DISTANCE = 0.10  # m: a correspondence is an inlier below this residual
FMR_THRESHOLD = 0.05  # a pair is "matched" when its inlier ratio exceeds this
RMSE_THRESHOLD = 0.2  # m: registration succeeds when the approximated RMSE is within this


# --------------------------------------------------------------------------- per pair


def inlier_ratio(
    src_corr: np.ndarray, tgt_corr: np.ndarray, transform_gt: np.ndarray, threshold: float = INLIER_DISTANCE
) -> float:
    """Fraction of correspondences with ``||T_gt src - tgt|| < threshold``.

    src_corr (K, 3), tgt_corr (K, 3): the corresponding points (source in its own frame);
    transform_gt (4, 4) maps source into target. Returns 0.0 when K == 0.
    """
    src_corr = np.asarray(src_corr, dtype=np.float64).reshape(-1, 3)
    tgt_corr = np.asarray(tgt_corr, dtype=np.float64).reshape(-1, 3)
    if len(src_corr) != len(tgt_corr):
        raise ValueError(f"src_corr has {len(src_corr)} rows but tgt_corr has {len(tgt_corr)}")
    if len(src_corr) == 0:
        return 0.0
    T = np.asarray(transform_gt, dtype=np.float64)
    res = np.linalg.norm(src_corr @ T[:3, :3].T + T[:3, 3] - tgt_corr, axis=1)
    return float(np.mean(res < threshold))


def feature_match_recall(inlier_ratios: Sequence[float], threshold: float = FMR_THRESHOLD) -> float:
    """Fraction (0..1) of pairs whose inlier ratio exceeds ``threshold``; NaN for no pairs."""
    irs = np.asarray(inlier_ratios, dtype=np.float64)
    return float(np.mean(irs > threshold)) if irs.size else float("nan")


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) as (w, x, y, z) with w >= 0 of rotation matrices (..., 3, 3).

    Shepperd's method: the largest of (w, x, y, z) is computed from the diagonal, the others from
    the off-diagonal sums, which is stable for every angle.
    """
    R = np.asarray(R, dtype=np.float64)
    shape = R.shape[:-2]
    m = R.reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    tr = m00 + m11 + m22
    case = np.argmax(np.stack([tr, m00, m11, m22], axis=1), axis=1)
    q = np.empty((len(m), 4))
    with np.errstate(invalid="ignore", divide="ignore"):
        s0 = 2.0 * np.sqrt(np.maximum(1.0 + tr, 0.0))
        s1 = 2.0 * np.sqrt(np.maximum(1.0 + m00 - m11 - m22, 0.0))
        s2 = 2.0 * np.sqrt(np.maximum(1.0 + m11 - m00 - m22, 0.0))
        s3 = 2.0 * np.sqrt(np.maximum(1.0 + m22 - m00 - m11, 0.0))
        cands = [
            np.stack([s0 / 4, (m21 - m12) / s0, (m02 - m20) / s0, (m10 - m01) / s0], 1),
            np.stack([(m21 - m12) / s1, s1 / 4, (m01 + m10) / s1, (m02 + m20) / s1], 1),
            np.stack([(m02 - m20) / s2, (m01 + m10) / s2, s2 / 4, (m12 + m21) / s2], 1),
            np.stack([(m10 - m01) / s3, (m02 + m20) / s3, (m12 + m21) / s3, s3 / 4], 1),
        ]
    for k in range(4):
        sel = case == k
        q[sel] = cands[k][sel]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(*shape, 4)


def transformation_error(delta: np.ndarray, info: np.ndarray) -> np.ndarray:
    """The 3DMatch approximation of the squared RMSE, ``e^T info e / info[0, 0]``.

    delta (..., 4, 4): ``inv(T_gt) @ T_est``; info (..., 6, 6) translation first. Returns (...).
    """
    delta = np.asarray(delta, dtype=np.float64)
    info = np.asarray(info, dtype=np.float64)
    q = rotation_to_quaternion(delta[..., :3, :3])
    e = np.concatenate([delta[..., :3, 3], q[..., 1:]], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):  # a zero matrix gives NaN: a failure
        return np.einsum("...i,...ij,...j->...", e, info, e) / info[..., 0, 0]


def registration_error(T_est: np.ndarray, T_gt: np.ndarray, info: np.ndarray) -> np.ndarray:
    """``transformation_error(inv(T_gt) @ T_est, info)`` for (..., 4, 4) stacks; returns (...)."""
    T_gt = np.asarray(T_gt, dtype=np.float64)
    return transformation_error(np.linalg.inv(T_gt) @ np.asarray(T_est, dtype=np.float64), info)


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Geodesic angle (...) in degrees between rotations (..., 3, 3)."""
    R_est = np.asarray(R_est, dtype=np.float64)
    R_gt = np.asarray(R_gt, dtype=np.float64)
    tr = np.einsum("...ij,...ij->...", R_est, R_gt)  # trace(R_est^T R_gt)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def translation_error(t_est: np.ndarray, t_gt: np.ndarray) -> np.ndarray:
    """Euclidean distance (...) between translations (..., 3), metres."""
    return np.linalg.norm(np.asarray(t_est, dtype=np.float64) - np.asarray(t_gt, dtype=np.float64), axis=-1)


def information_matrix(points: np.ndarray) -> np.ndarray:
    """The 6x6 ``gt.info`` matrix (translation first) of ground-truth correspondences.

    points (M, 3): the corresponding points in the frame the error is measured in. Returns
    ``sum_p G_p^T G_p`` with ``G_p = [I | -[p]x]``, so ``info[0, 0] = M``.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(p)
    s = p.sum(0)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    info = np.zeros((6, 6))
    info[:3, :3] = n * np.eye(3)
    # -sum [p]x
    info[:3, 3:] = -np.array([[0.0, -s[2], s[1]], [s[2], 0.0, -s[0]], [-s[1], s[0], 0.0]])
    info[3:, :3] = info[:3, 3:].T
    info[3:, 3:] = np.array(
        [
            [np.sum(y * y + z * z), -np.sum(x * y), -np.sum(x * z)],
            [-np.sum(x * y), np.sum(x * x + z * z), -np.sum(y * z)],
            [-np.sum(x * z), -np.sum(y * z), np.sum(x * x + y * y)],
        ]
    )
    return info


def counted_mask(pairs: Sequence[PairRecord], predator_variant: bool = False) -> np.ndarray:
    """(P,) bool: which pairs count in the registration recall (not adjacent: ``j - i > 1``).

    With ``predator_variant`` the first listed pair never counts (see the module docstring).
    """
    mask = np.array([p.j - p.i > 1 for p in pairs], dtype=bool)
    if predator_variant and len(mask):
        mask[0] = False
    return mask


# --------------------------------------------------------------------------- benchmark files


@dataclass(frozen=True)
class SceneGT:
    """The ground truth of one scene: pairs in ``gt.log`` order and their information matrices.

    ``transforms`` (P, 4, 4) map fragment j into fragment i; ``infos`` (P, 6, 6).
    """

    scene: str
    pairs: tuple[PairRecord, ...]
    transforms: np.ndarray
    infos: np.ndarray

    @property
    def n_fragments(self) -> int:
        return self.pairs[0].n_fragments if self.pairs else 0

    def keys(self) -> list[tuple[int, int]]:
        return [(p.i, p.j) for p in self.pairs]


def load_scene_gt(scene_dir: str | os.PathLike, scene: str | None = None) -> SceneGT:
    """Read and check ``<scene_dir>/gt.log`` and ``gt.info`` (every pair needs its 6x6 matrix)."""
    scene_dir = Path(scene_dir)
    scene = scene or scene_dir.name
    log_path, info_path = scene_dir / "gt.log", scene_dir / "gt.info"
    for path in (log_path, info_path):
        if not path.is_file():
            raise DataError(path, "file is missing (a benchmark scene needs gt.log and gt.info)")
    pairs = read_gt_log(log_path, scene)
    if not pairs:
        raise DataError(log_path, "holds no pairs")
    infos = read_gt_info(info_path)
    seen: set[tuple[int, int]] = set()
    mats = []
    for p in pairs:
        if (p.i, p.j) in seen:
            raise DataError(log_path, f"pair {p.i} {p.j} is listed twice")
        seen.add((p.i, p.j))
        check_rigid(p.transform, f"{log_path} (pair {p.i} {p.j})", tol=1e-2)
        M = infos.get((p.i, p.j))
        if M is None:
            raise DataError(info_path, f"no information matrix for pair {p.i} {p.j} of gt.log")
        if not np.all(np.isfinite(M)) or M[0, 0] < 0:
            raise DataError(info_path, f"information matrix of pair {p.i} {p.j} is not valid (NaN or info[0,0] < 0)")
        if M[0, 0] == 0:
            # The official 3DLoMatch file has one such pair (home_md 23 25): its error is 0/0,
            # so it can never be registered; the protocol counts it as a failure.
            log.warning("%s: pair %d %d has a zero information matrix; it always counts as a failure",
                        info_path, p.i, p.j)
        mats.append(M)
    return SceneGT(scene, tuple(pairs), np.stack([p.transform for p in pairs]), np.stack(mats))


def benchmark_scenes(benchmark_dir: str | os.PathLike) -> list[str]:
    """Sorted names of the scene folders of a benchmark folder (``<dir>/<scene>/gt.log``)."""
    d = Path(benchmark_dir)
    if not d.is_dir():
        raise DataError(d, "benchmark folder does not exist")
    scenes = sorted(p.name for p in d.iterdir() if p.is_dir())
    if not scenes:
        raise DataError(d, "benchmark folder holds no scene folders (<scene>/gt.log, gt.info)")
    return scenes


def load_benchmark(benchmark_dir: str | os.PathLike, scenes: Sequence[str] | None = None) -> dict[str, SceneGT]:
    """All scenes of a benchmark folder, checked before any work starts."""
    d = Path(benchmark_dir)
    names = list(scenes) if scenes is not None else benchmark_scenes(d)
    if scenes is not None and not d.is_dir():
        raise DataError(d, "benchmark folder does not exist")
    return {s: load_scene_gt(d / s, s) for s in names}


def read_estimates(path: str | os.PathLike, scene: str = "") -> dict[tuple[int, int], np.ndarray]:
    """``est.log`` -> {(i, j): 4x4 mapping j into i}; malformed, duplicated or non-rigid -> DataError."""
    path = Path(path)
    out: dict[tuple[int, int], np.ndarray] = {}
    for rec in read_gt_log(path, scene):
        key = (rec.i, rec.j)
        if key in out:
            raise DataError(path, f"pair {rec.i} {rec.j} has two estimates")
        out[key] = check_rigid(rec.transform, f"{path} (pair {rec.i} {rec.j})", tol=1e-2)
    return out


def load_estimates(
    estimate_dir: str | os.PathLike, scenes: Iterable[str]
) -> tuple[dict[str, dict[tuple[int, int], np.ndarray]], list[str]]:
    """Read ``<estimate_dir>/<scene>/est.log`` for every scene.

    Returns (estimates per scene, scenes whose est.log is missing: all their pairs fail).
    """
    d = Path(estimate_dir)
    if not d.is_dir():
        raise DataError(d, "estimate folder does not exist")
    out, missing = {}, []
    for s in scenes:
        f = d / s / "est.log"
        if f.is_file():
            out[s] = read_estimates(f, s)
        else:
            log.warning("%s: missing, every pair of scene %s counts as a failure", f, s)
            out[s] = {}
            missing.append(s)
    return out, missing


def write_estimates(
    path: str | os.PathLike, gt: SceneGT, estimates: Mapping[tuple[int, int], np.ndarray]
) -> None:
    """Write ``est.log`` in ``gt.log`` order (pairs without an estimate are left out)."""
    recs = [
        PairRecord(gt.scene, p.i, p.j, np.asarray(estimates[(p.i, p.j)], dtype=np.float64), n_fragments=p.n_fragments)
        for p in gt.pairs
        if (p.i, p.j) in estimates
    ]
    write_gt_log(path, recs)


# --------------------------------------------------------------------------- scoring


@dataclass
class SceneScore:
    """Per-pair results of one scene, arrays aligned with ``gt.pairs`` (P,)."""

    scene: str
    counted: np.ndarray  # bool: counts in the recall
    present: np.ndarray  # bool: an estimate exists
    error: np.ndarray  # float: approximated squared RMSE (NaN when missing)
    success: np.ndarray  # bool: present and error <= 0.2**2
    rre: np.ndarray  # degrees (NaN when missing)
    rte: np.ndarray  # metres (NaN when missing)

    @property
    def n_counted(self) -> int:
        return int(self.counted.sum())

    @property
    def n_success(self) -> int:
        return int((self.success & self.counted).sum())

    @property
    def recall(self) -> float:
        """Recall in %, NaN when the scene has no counted pair."""
        return 100.0 * self.n_success / self.n_counted if self.n_counted else float("nan")


def score_scene(
    gt: SceneGT,
    estimates: Mapping[tuple[int, int], np.ndarray],
    predator_variant: bool = False,
    threshold: float = RMSE_THRESHOLD,
) -> SceneScore:
    """Score one scene's estimates {(i, j): 4x4} against its ground truth."""
    P = len(gt.pairs)
    present = np.array([(p.i, p.j) in estimates for p in gt.pairs], dtype=bool)
    T_est = np.stack([np.asarray(estimates[k], dtype=np.float64) if ok else np.eye(4)
                      for k, ok in zip(gt.keys(), present)]) if P else np.zeros((0, 4, 4))
    err = np.full(P, np.nan)
    rre = np.full(P, np.nan)
    rte = np.full(P, np.nan)
    if present.any():
        err[present] = registration_error(T_est[present], gt.transforms[present], gt.infos[present])
        rre[present] = rotation_error_deg(T_est[present, :3, :3], gt.transforms[present, :3, :3])
        rte[present] = translation_error(T_est[present, :3, 3], gt.transforms[present, :3, 3])
    success = present & (np.nan_to_num(err, nan=np.inf) <= threshold**2)
    return SceneScore(gt.scene, counted_mask(gt.pairs, predator_variant), present, err, success, rre, rte)


@dataclass
class BenchmarkScore:
    """Registration recall and errors of one benchmark (percentages in %)."""

    rr: float
    rr_pair: float
    scenes: dict[str, float]
    rre: float
    rte: float
    rre_pair_mean: float
    rte_pair_mean: float
    n_pairs: int
    n_counted: int
    n_success: int
    n_missing: int
    missing_scenes: list[str] = field(default_factory=list)
    predator_variant: bool = False
    scene_scores: dict[str, SceneScore] = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-pair arrays)."""
        return {
            "rr": _r(self.rr),
            "rr_pair": _r(self.rr_pair),
            "scenes": {k: _r(v) for k, v in self.scenes.items()},
            "rre": _r(self.rre),
            "rte": _r(self.rte),
            "rre_pair_mean": _r(self.rre_pair_mean),
            "rte_pair_mean": _r(self.rte_pair_mean),
            "n_pairs": self.n_pairs,
            "n_counted": self.n_counted,
            "n_success": self.n_success,
            "n_missing": self.n_missing,
            "missing_scenes": list(self.missing_scenes),
            "predator_variant": self.predator_variant,
            "protocol": "3DMatch: RMSE(gt.info) <= 0.2 m, pairs with j - i > 1, recall averaged per scene",
        }


def _r(v: float, nd: int = 6) -> float | None:
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else round(float(v), nd)


def _nanmean(vals: Sequence[float]) -> float:
    arr = np.asarray([v for v in vals if not math.isnan(v)], dtype=np.float64)
    return float(arr.mean()) if arr.size else float("nan")


def summarize(scores: Mapping[str, SceneScore], predator_variant: bool = False,
              missing_scenes: Sequence[str] = ()) -> BenchmarkScore:
    """Aggregate per-scene scores: recall per scene then mean; RRE/RTE medians per scene then mean."""
    scenes = {s: sc.recall for s, sc in scores.items()}
    n_counted = sum(sc.n_counted for sc in scores.values())
    n_success = sum(sc.n_success for sc in scores.values())
    med_re, med_te, all_re, all_te = [], [], [], []
    for sc in scores.values():
        ok = sc.success & sc.counted
        if ok.any():
            med_re.append(float(np.median(sc.rre[ok])))
            med_te.append(float(np.median(sc.rte[ok])))
            all_re.extend(sc.rre[ok].tolist())
            all_te.extend(sc.rte[ok].tolist())
        elif predator_variant:  # Predator's script averages a 0 in for such scenes
            med_re.append(0.0)
            med_te.append(0.0)
    return BenchmarkScore(
        rr=_nanmean(list(scenes.values())),
        rr_pair=100.0 * n_success / n_counted if n_counted else float("nan"),
        scenes=scenes,
        rre=_nanmean(med_re),
        rte=_nanmean(med_te),
        rre_pair_mean=float(np.mean(all_re)) if all_re else float("nan"),
        rte_pair_mean=float(np.mean(all_te)) if all_te else float("nan"),
        n_pairs=sum(len(sc.counted) for sc in scores.values()),
        n_counted=n_counted,
        n_success=n_success,
        n_missing=int(sum((~sc.present).sum() for sc in scores.values())),
        missing_scenes=list(missing_scenes),
        predator_variant=predator_variant,
        scene_scores=dict(scores),
    )


def score_benchmark(
    gt: Mapping[str, SceneGT],
    estimates: Mapping[str, Mapping[tuple[int, int], np.ndarray]],
    predator_variant: bool = False,
    missing_scenes: Sequence[str] = (),
    threshold: float = RMSE_THRESHOLD,
) -> BenchmarkScore:
    """Score in-memory estimates {scene: {(i, j): 4x4}} (absent scene or pair = failure)."""
    scores = {s: score_scene(g, estimates.get(s, {}), predator_variant, threshold) for s, g in gt.items()}
    return summarize(scores, predator_variant, missing_scenes)


def score_directories(
    benchmark_dir: str | os.PathLike,
    estimate_dir: str | os.PathLike,
    predator_variant: bool = False,
    threshold: float = RMSE_THRESHOLD,
) -> BenchmarkScore:
    """Score ``<estimate_dir>/<scene>/est.log`` against ``<benchmark_dir>/<scene>/gt.log|gt.info``.

    Every input file is read and checked before scoring; a missing est.log fails its scene.
    """
    gt = load_benchmark(benchmark_dir)
    est, missing = load_estimates(estimate_dir, gt.keys())
    return score_benchmark(gt, est, predator_variant, missing, threshold)


def scene_averaged(values: Mapping[str, Sequence[float]]) -> float:
    """Mean over scenes of the per-scene mean (scenes without values are skipped)."""
    return _nanmean([float(np.mean(v)) for v in values.values() if len(v)])


def correspondence_metrics(
    inlier_ratios: Mapping[str, Sequence[float]], threshold: float = FMR_THRESHOLD
) -> dict[str, float]:
    """IR and FMR (in %) from per-scene lists of per-pair inlier ratios, averaged per scene then
    over scenes, plus the pooled pair-level FMR."""
    pooled = [v for vals in inlier_ratios.values() for v in vals]
    return {
        "ir": 100.0 * scene_averaged(inlier_ratios),
        "fmr": 100.0 * _nanmean([feature_match_recall(v, threshold) for v in inlier_ratios.values() if len(v)]),
        "fmr_pair": 100.0 * feature_match_recall(pooled, threshold),
    }
