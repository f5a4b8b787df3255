"""Choosing the N points per fragment that registration uses (Predator's protocol).

Modes
-----
* ``prob``: probabilistic sampling without replacement, probability proportional to the score
  (overlap x matchability in Predator). Implemented with Gumbel-top-k (Efraimidis-Spirakis):
  the N largest ``log(score) + Gumbel noise`` are exactly a sequential draw without replacement.
  Points with score 0 are taken only when fewer than N points have a positive score.
* ``topk``: the N highest scores (ties broken by index).
* ``random``: N points uniformly without replacement (scores ignored).

A fragment with fewer than N points (``fewer`` setting, ``registration.fewer_points``):

* ``with_replacement``: N points drawn uniformly with replacement, as Predator's evaluation script
  (``np.random.choice(n, N)``; PCR-CG evaluates with the same script);
* ``whole``: every point once (fewer than N points).

A fragment with exactly N points is used whole either way (Predator samples all N without
replacement).
"""

from __future__ import annotations

import numpy as np

from pcrcg.errors import ConfigError

SAMPLING_MODES = ("prob", "topk", "random")
FEWER_POINTS = ("with_replacement", "whole")


def sample_indices(scores: np.ndarray, n: int, mode: str, rng: np.random.Generator,
                   fewer: str = "whole") -> np.ndarray:
    """Indices int64, sorted ascending, of the points to keep; scores (N,) >= 0.

    ``n`` indices, except for a fragment with fewer points under ``fewer="whole"`` (then all N);
    with ``fewer="with_replacement"`` such a fragment gives ``n`` indices with repeats.
    """
    if mode not in SAMPLING_MODES:
        raise ConfigError("registration.sampling", mode, " | ".join(SAMPLING_MODES))
    if fewer not in FEWER_POINTS:
        raise ConfigError("registration.fewer_points", fewer, " | ".join(FEWER_POINTS))
    if n < 1:
        raise ConfigError("n_points", n, ">= 1")
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    N = len(scores)
    if N < n and fewer == "with_replacement" and N > 0:
        return np.sort(rng.integers(0, N, size=n)).astype(np.int64)
    if N <= n:
        return np.arange(N, dtype=np.int64)
    if mode == "random":
        return np.sort(rng.choice(N, size=n, replace=False)).astype(np.int64)
    s = np.where(np.isfinite(scores), np.maximum(scores, 0.0), 0.0)
    if mode == "topk":
        return np.sort(np.argsort(-s, kind="stable")[:n]).astype(np.int64)
    if s.sum() <= 0:  # no information: uniform
        return np.sort(rng.choice(N, size=n, replace=False)).astype(np.int64)
    with np.errstate(divide="ignore"):
        keys = np.log(s) + rng.gumbel(size=N)
    return np.sort(np.argpartition(-keys, n - 1)[:n]).astype(np.int64)
