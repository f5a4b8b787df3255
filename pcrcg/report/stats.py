"""Is a difference between two rows more than test-pair noise? (pure NumPy)

The statistic is the 3DMatch protocol's: registration recall (or feature-matching recall) is
the mean outcome of a scene's pairs, then the mean over scenes (``scene_average=True``, what
``<benchmark>/rr_<N>`` is); ``scene_average=False`` gives the pooled, pair-level recall
(``rr_pair``). Outcomes are per pair in [0, 1] (1 = registered); recalls are in %.

Paired bootstrap of a difference ``stat(b) - stat(a)`` over the same test pairs
--------------------------------------------------------------------------------
Each of ``n_boot`` replicates draws, within every scene, as many pairs as the scene has, with
replacement (stratified: the scenes and their weights stay fixed, as the protocol's average
over scenes does), takes *the same* pairs for both methods (paired), and recomputes the
statistic exactly as above. The interval is the percentile interval of the replicates
(``level``, 95 % by default); the point estimate is the difference on the pairs as they are.
A fixed ``seed`` gives the same interval every time.

Several seeds
-------------
Where several runs share a config except ``seed`` (one config hash per seed), the point estimate is the mean
over seeds of the recall difference. With ``seeds="resample"`` (the report's default, ``stats.seeds``) and the
two methods' runs given seed against seed (``a[i]`` and ``b[i]`` trained with the same seed, two or more
seeds), each replicate first draws as many seeds as there are, with replacement (the same draw for both
methods), then the pairs within scenes, and recomputes the difference averaged over the drawn seeds: a
two-stage (seeds, then pairs) bootstrap, so that the interval covers training randomness as far as the seeds
show it, not only test-pair sampling. With two or three seeds the seed stage has few distinct draws and the
interval is coarse and wide where the seeds disagree, which is the point: a difference that one seed shows
and another reverses is not resolved. With ``seeds="pool"`` (or seeds that are not matched) each method's
outcome of a pair is its mean over its seeds (:func:`pool_seeds`: the fraction of seeds that registered it)
and only the pairs are resampled: the interval is then about test-pair sampling given the trained models.
One seed: both are the plain paired bootstrap above (the same replicates).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

N_BOOT = 2000
LEVEL = 0.95
SEED = 0

HOLDS = "holds"
REVERSED = "reversed"
NOISE = "within noise"
SEED_MODES = ("resample", "pool")
PAPER_TIE = "tie in the paper"
NO_PAPER = "not in the paper"
VERDICTS = (HOLDS, REVERSED, NOISE, PAPER_TIE, NO_PAPER)


@dataclass(frozen=True)
class Interval:
    """``diff`` = stat(b) − stat(a) in %, its bootstrap interval [lo, hi] at ``level``."""

    diff: float
    lo: float
    hi: float
    level: float
    n_pairs: int
    n_scenes: int
    n_boot: int
    seed: int
    n_seeds: int = 1  # seeds behind each side (per pair, pooled or resampled)
    seed_mode: str = "pool"  # resample: seeds drawn seed against seed, then pairs; pool: seeds averaged per pair

    @property
    def seeds_label(self) -> str:
        """How the seeds entered the interval, for the CSV files: ``resample (2)``, ``pool (1)``."""
        return f"{self.seed_mode} ({self.n_seeds})"

    @property
    def excludes_zero(self) -> bool:
        return self.lo > 0 or self.hi < 0


def _groups(scenes: Sequence) -> list[np.ndarray]:
    """Indices of each scene's pairs, scenes in sorted order (deterministic)."""
    _, inverse = np.unique(np.asarray(scenes, dtype=str), return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.flatnonzero(np.diff(inverse[order])) + 1
    return np.split(order, bounds) if len(order) else []


def _as_outcomes(x: np.ndarray | Sequence[float], n: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 2:  # runs (seeds) x pairs
        a = pool_seeds(a)
    if a.shape != (n,):
        raise ValueError(f"{name} has shape {a.shape}; expected ({n},) or (runs, {n}) like scenes")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds NaN or inf")
    return a


def pool_seeds(outcomes: np.ndarray) -> np.ndarray:
    """(runs, P) outcomes of one method's seeds -> (P,) mean per pair (see module docstring)."""
    a = np.asarray(outcomes, dtype=np.float64)
    if a.ndim != 2 or a.shape[0] == 0:
        raise ValueError(f"outcomes of the seeds must be (runs, pairs), got {a.shape}")
    return a.mean(axis=0)


def recall(outcomes: np.ndarray | Sequence[float], scenes: Sequence, scene_average: bool = True) -> float:
    """Recall in % of per-pair outcomes: mean per scene, then over scenes (or pooled)."""
    scenes = np.asarray(scenes)
    a = _as_outcomes(outcomes, len(scenes), "outcomes")
    if not len(a):
        return float("nan")
    if not scene_average:
        return 100.0 * float(a.mean())
    return 100.0 * float(np.mean([a[g].mean() for g in _groups(scenes)]))


def paired_bootstrap(
    a: np.ndarray | Sequence[float],
    b: np.ndarray | Sequence[float],
    scenes: Sequence,
    *,
    n_boot: int = N_BOOT,
    seed: int = SEED,
    level: float = LEVEL,
    scene_average: bool = True,
    seeds: str = "pool",
) -> Interval:
    """Bootstrap interval of ``recall(b) - recall(a)`` over the same pairs (see module docstring).

    a, b: (P,) outcomes of the two methods on the same pairs, or (S, P): S seeds each; scenes: (P,) scene of
    each pair (strata). Pairs resampled within scenes when ``scene_average``, over all pairs otherwise.
    ``seeds``: ``resample`` (a[i] and b[i] are one seed's runs: seeds drawn too, when both have the same
    S >= 2 rows) or ``pool`` (each method's seeds averaged per pair first).
    """
    if seeds not in SEED_MODES:
        raise ValueError(f"seeds must be one of {SEED_MODES}, got {seeds!r}")
    scenes = np.asarray(scenes)
    P = len(scenes)
    a2, b2 = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    matched = seeds == "resample" and a2.ndim == 2 and a2.shape == b2.shape and a2.shape[0] >= 2
    a = _as_outcomes(a, P, "a")
    b = _as_outcomes(b, P, "b")
    if P == 0:
        raise ValueError("no pairs to resample")
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")
    n_boot = int(n_boot)
    if n_boot < 1:
        raise ValueError(f"n_boot must be >= 1, got {n_boot}")
    rng = np.random.default_rng(int(seed))
    d = b - a  # the statistic is linear: the difference of recalls is the recall of the differences
    groups = _groups(scenes) if scene_average else [np.arange(P)]
    per_group = np.empty((n_boot, len(groups)))
    if matched:  # (n_boot, P): each replicate's differences averaged over its draw of seeds
        S = a2.shape[0]
        counts = np.stack([np.bincount(row, minlength=S) for row in rng.integers(0, S, size=(n_boot, S))])
        d_rep = (counts / S) @ (b2 - a2)
    for k, g in enumerate(groups):
        draw = rng.integers(0, len(g), size=(n_boot, len(g)))
        if matched:
            per_group[:, k] = np.take_along_axis(d_rep[:, g], draw, axis=1).mean(axis=1)
        else:
            per_group[:, k] = d[g][draw].mean(axis=1)
    reps = 100.0 * per_group.mean(axis=1)
    point = 100.0 * float(np.mean([d[g].mean() for g in groups]))
    tail = 100.0 * (1.0 - level) / 2.0
    lo, hi = np.percentile(reps, [tail, 100.0 - tail])
    n_seeds = a2.shape[0] if matched else (min(a2.shape[0], b2.shape[0]) if a2.ndim == 2 and b2.ndim == 2 else 1)
    return Interval(point, float(lo), float(hi), float(level), P, len(groups), n_boot, int(seed), int(n_seeds),
                    "resample" if matched else "pool")


def seed_rule_text(intervals: Sequence[Interval | None]) -> str:
    """How the seeds entered these intervals, for a report's intro."""
    if any(iv is not None and iv.seed_mode == "resample" for iv in intervals):
        return ("where both rows ran the same two or more seeds, the seeds drawn too (seed against seed), then the "
                "pairs, so that the interval covers the spread between seeds; else the seeds pooled per pair")
    return "seeds pooled per pair, over the seeds both rows ran"


def mean_std(values: Sequence[float]) -> tuple[float, float, int]:
    """(mean, sample std, n) of finite values; std 0 for one value, NaN for none."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(float(x))], dtype=np.float64)
    if not v.size:
        return float("nan"), float("nan"), 0
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else 0.0, int(v.size)


def verdict(paper_diff: float | None, interval: Interval | None) -> str | None:
    """How our interval stands to the paper's ordering of the two rows (``paper_diff`` = paper's b − a).

    ``holds``: the interval excludes 0 on the side of the paper's difference; ``reversed``: on the other side;
    ``within noise``: it contains 0; ``tie in the paper`` / ``not in the paper``: no ordering to
    test. None when there is no interval (the caller says why).
    """
    if paper_diff is None or (isinstance(paper_diff, float) and math.isnan(paper_diff)):
        return NO_PAPER
    if round(float(paper_diff), 6) == 0:
        return PAPER_TIE
    if interval is None:
        return None
    sign = np.sign(paper_diff)
    if interval.lo > 0:
        return HOLDS if sign > 0 else REVERSED
    if interval.hi < 0:
        return HOLDS if sign < 0 else REVERSED
    return NOISE
