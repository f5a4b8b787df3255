"""Choosing the N points per fragment that registration uses (Predator's protocol).

Modes
-----
* ``prob``: probabilistic sampling without replacement, probability proportional to the score
  (overlap x matchability in Predator). Implemented with Gumbel-top-k (Efraimidis-Spirakis):
  the N largest ``log(score) + Gumbel noise`` are exactly a sequential draw without replacement.
  Points with score 0 are taken only when fewer than N points have a positive score.
* ``topk``: the N highest scores (ties broken by index).
* ``random``: N points uniformly without replacement (scores ignored).

A fragment with at most N points is used whole, as in Predator.
"""

from __future__ import annotations

import numpy as np

from pcrcg.errors import ConfigError

SAMPLING_MODES = ("prob", "topk", "random")


def sample_indices(scores: np.ndarray, n: int, mode: str, rng: np.random.Generator) -> np.ndarray:
    """Indices (min(n, N),) int64, sorted ascending, of the points to keep; scores (N,) >= 0."""
    if mode not in SAMPLING_MODES:
        raise ConfigError("registration.sampling", mode, " | ".join(SAMPLING_MODES))
    if n < 1:
        raise ConfigError("n_points", n, ">= 1")
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    N = len(scores)
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
