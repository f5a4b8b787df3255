"""Registration of a pair from a model's own point correspondences (CoFiNet's protocol).

For one N: if the model gave more than N correspondences, N are drawn without replacement with
probability proportional to their confidence (CoFiNet's benchmark script), else all are kept; the
configured RANSAC (:mod:`pcrcg.registration.ransac`, ours or Open3D's) fits the transform on them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcrcg.device import torch_threads
from pcrcg.registration.feature_registration import RegistrationConfig, sample_and_ransac_seeds
from pcrcg.registration.ransac import RansacResult, ransac, ransac_open3d


@dataclass
class CorrespondenceRegistration:
    """transform (4, 4) source -> target; used (K,) indices of the correspondences RANSAC saw."""

    transform: np.ndarray
    used: np.ndarray
    ransac: RansacResult | None


def sample_correspondences(scores: np.ndarray, n_points: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of at most ``n_points`` correspondences, drawn without replacement by confidence."""
    c = len(scores)
    if c <= n_points:
        return np.arange(c)
    w = np.clip(np.nan_to_num(np.asarray(scores, np.float64), nan=0.0, posinf=0.0), 0.0, None)
    w = w + max(float(w.max()), 1.0) * 1e-12  # every candidate keeps a (tiny) chance: N draws always exist
    return np.sort(rng.choice(c, size=int(n_points), replace=False, p=w / w.sum()))


def register_correspondences(pairs: np.ndarray, scores: np.ndarray, n_points: int, cfg: RegistrationConfig | None = None,
                             seed: int | np.random.SeedSequence = 0) -> CorrespondenceRegistration:
    """pairs (C, 6) source xyz, target xyz; scores (C,) confidences -> :class:`CorrespondenceRegistration`
    (the identity when fewer than 3 correspondences remain)."""
    cfg = cfg or RegistrationConfig()
    pairs = np.asarray(pairs, np.float32).reshape(-1, 6)
    s_sample, s_ransac = sample_and_ransac_seeds(seed)
    used = sample_correspondences(np.asarray(scores).reshape(-1), int(n_points), np.random.default_rng(s_sample))
    if len(used) < 3:
        return CorrespondenceRegistration(np.eye(4), used, None)
    sp, tp = np.ascontiguousarray(pairs[used, :3]), np.ascontiguousarray(pairs[used, 3:])
    idx = np.arange(len(used))
    corr = np.stack([idx, idx], 1)
    with torch_threads(cfg.ransac.threads, cfg.device):
        if cfg.backend == "torch":
            res = ransac(sp, tp, corr, cfg.ransac, seed=np.random.default_rng(s_ransac), device=cfg.device)
        else:
            res = ransac_open3d(sp, tp, corr, cfg.ransac, seed=int(s_ransac.generate_state(1)[0] & 0x7FFFFFFF))
    return CorrespondenceRegistration(np.asarray(res.transform, np.float64), used, res)
