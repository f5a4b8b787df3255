"""Feature registration: Predator's registration of a pair from per-point network outputs.

For one pair and one N: sample N points per fragment by ``overlap x matchability``
(:mod:`pcrcg.registration.sampling`), match their descriptors by nearest neighbour (optionally
mutual, :mod:`pcrcg.registration.matching`), and estimate the transform with RANSAC
(:mod:`pcrcg.registration.ransac`, ours or Open3D's).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field, fields
from typing import Mapping

import numpy as np
import torch

from pcrcg.config import N_POINTS
from pcrcg.device import torch_threads
from pcrcg.errors import ConfigError
from pcrcg.registration.matching import match_descriptors
from pcrcg.registration.ransac import RansacConfig, RansacResult, ransac, ransac_open3d
from pcrcg.registration.sampling import FEWER_POINTS, SAMPLING_MODES, sample_indices

BACKENDS = ("torch", "open3d")


@dataclass
class FragmentOutput:
    """What the network gives for one fragment of a pair: the model stage's output and the
    registration stage's input (:meth:`pcrcg.models.module.PCRCGModule.predict_pair`).

    points (N, 3) float32 in the fragment's own frame; descriptors (N, D) float32 (unit norm from
    the models); overlap (N,) and matchability (N,) float32 scores in [0, 1]. Arrays and tensors
    given are made float32 numpy arrays and their shapes checked.
    """

    points: np.ndarray
    descriptors: np.ndarray
    overlap: np.ndarray
    matchability: np.ndarray

    def __post_init__(self) -> None:
        self.points = _np(self.points, np.float32)
        self.descriptors = _np(self.descriptors, np.float32)
        self.overlap = _np(self.overlap, np.float32).reshape(-1)
        self.matchability = _np(self.matchability, np.float32).reshape(-1)
        n = len(self.points)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points must be (N, 3), got {self.points.shape}")
        if self.descriptors.ndim != 2 or len(self.descriptors) != n:
            raise ValueError(f"descriptors must be ({n}, D), got {self.descriptors.shape}")
        if len(self.overlap) != n or len(self.matchability) != n:
            raise ValueError(f"overlap and matchability must be ({n},), got {self.overlap.shape} and {self.matchability.shape}")

    def scores(self) -> np.ndarray:
        """(N,) sampling scores: overlap x matchability."""
        return self.overlap * self.matchability

    def as_dict(self) -> dict[str, np.ndarray]:
        return {"points": self.points, "descriptors": self.descriptors, "overlap": self.overlap,
                "matchability": self.matchability}


def _np(x, dtype) -> np.ndarray:
    if torch.is_tensor(x):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


@dataclass
class RegistrationConfig:
    """Settings of Predator's registration (the ``registration`` config group).

    sampling: ``prob`` | ``topk`` | ``random``; fewer_points: a fragment with fewer than N points gives
    N drawn uniformly ``with_replacement`` (Predator's script) or is used ``whole``; mutual: mutual nearest neighbours only (falls back
    to all matches when fewer than ``3 * ransac_n`` survive, like Open3D); backend: ``torch``
    (ours) | ``open3d`` (reference); device: torch device of matching and RANSAC.
    """

    sampling: str = "prob"
    fewer_points: str = "whole"
    mutual: bool = False
    backend: str = "torch"
    device: str = "cpu"
    n_points: tuple[int, ...] = N_POINTS
    ransac: RansacConfig = field(default_factory=RansacConfig)

    def __post_init__(self) -> None:
        if self.sampling not in SAMPLING_MODES:
            raise ConfigError("registration.sampling", self.sampling, " | ".join(SAMPLING_MODES))
        if self.fewer_points not in FEWER_POINTS:
            raise ConfigError("registration.fewer_points", self.fewer_points, " | ".join(FEWER_POINTS))
        if self.backend not in BACKENDS:
            raise ConfigError("registration.backend", self.backend, " | ".join(BACKENDS))
        self.n_points = tuple(int(n) for n in self.n_points)
        if not self.n_points or min(self.n_points) < 3:
            raise ConfigError("registration.n_points", list(self.n_points), "a non-empty list of integers >= 3")
        if isinstance(self.ransac, Mapping):
            self.ransac = RansacConfig.from_dict(dict(self.ransac))
        if self.backend == "open3d" and self.ransac.max_validation is not None:
            raise ConfigError("registration.ransac.max_validation", self.ransac.max_validation,
                              "null with registration.backend=open3d (Open3D >= 0.12 has no validation budget; "
                              "the torch backend reproduces Open3D 0.10's)")

    @classmethod
    def from_dict(cls, d: Mapping) -> "RegistrationConfig":
        """From the ``registration`` config node (extra keys of other sections are ignored)."""
        names = {f.name for f in fields(cls)}
        kw = {k: d[k] for k in d if k in names}
        if "ransac" in kw:
            kw["ransac"] = RansacConfig.from_dict(dict(kw["ransac"]))
        if "n_points" in kw:
            kw["n_points"] = tuple(kw["n_points"])
        return cls(**kw)


@dataclass
class FeatureRegistration:
    """Result of :func:`register_features`.

    transform (4, 4) maps source into target; src_idx (n,) / tgt_idx (m,) the sampled point
    indices; correspondences (K, 2) indices into the *full* fragments (source, target).
    """

    transform: np.ndarray
    src_idx: np.ndarray
    tgt_idx: np.ndarray
    correspondences: np.ndarray
    ransac: RansacResult


def pair_seed(seed: int, scene: str, i: int, j: int, n_points: int) -> np.random.SeedSequence:
    """A seed that depends only on (seed, pair, N), never on the order pairs are processed in."""
    return np.random.SeedSequence([int(seed) & 0xFFFFFFFF, zlib.crc32(scene.encode()), int(i), int(j), int(n_points)])


def sample_and_ransac_seeds(seed: int | np.random.SeedSequence) -> tuple[np.random.SeedSequence, np.random.SeedSequence]:
    """The two child seeds of a registration (sampling, RANSAC), spawned from a copy of ``seed``: spawning
    advances a ``SeedSequence``, so a caller that registers twice with the same one (two settings compared
    on one pair) would otherwise get other samples the second time."""
    if isinstance(seed, np.random.SeedSequence):
        ss = np.random.SeedSequence(seed.entropy, spawn_key=seed.spawn_key, pool_size=seed.pool_size)
    else:
        ss = np.random.SeedSequence(int(seed))
    s_sample, s_ransac = ss.spawn(2)
    return s_sample, s_ransac


def register_features(
    src: FragmentOutput,
    tgt: FragmentOutput,
    n_points: int,
    cfg: RegistrationConfig | None = None,
    seed: int | np.random.SeedSequence = 0,
) -> FeatureRegistration:
    """Register one pair: sample ``n_points`` per fragment, match, RANSAC."""
    cfg = cfg or RegistrationConfig()
    with torch_threads(cfg.ransac.threads, cfg.device):
        return _register_features(src, tgt, n_points, cfg, seed)


def _register_features(src, tgt, n_points, cfg, seed) -> FeatureRegistration:
    s_sample, s_ransac = sample_and_ransac_seeds(seed)
    rng = np.random.default_rng(s_sample)
    src_idx = sample_indices(src.scores(), n_points, cfg.sampling, rng, cfg.fewer_points)
    tgt_idx = sample_indices(tgt.scores(), n_points, cfg.sampling, rng, cfg.fewer_points)
    sp, tp = src.points[src_idx], tgt.points[tgt_idx]
    ids = {"src_ids": src_idx, "tgt_ids": tgt_idx}  # a sample with replacement: each point matched once
    corr = match_descriptors(src.descriptors[src_idx], tgt.descriptors[tgt_idx], mutual=cfg.mutual, device=cfg.device, **ids)
    if cfg.mutual and len(corr) < 3 * cfg.ransac.ransac_n:
        corr = match_descriptors(src.descriptors[src_idx], tgt.descriptors[tgt_idx], mutual=False, device=cfg.device, **ids)
    if cfg.backend == "torch":
        res = ransac(sp, tp, corr, cfg.ransac, seed=np.random.default_rng(s_ransac), device=cfg.device)
    else:
        res = ransac_open3d(sp, tp, corr, cfg.ransac, seed=int(s_ransac.generate_state(1)[0] & 0x7FFFFFFF))
    full = np.stack([src_idx[corr[:, 0]], tgt_idx[corr[:, 1]]], 1) if len(corr) else np.zeros((0, 2), np.int64)
    return FeatureRegistration(res.transform, src_idx, tgt_idx, full, res)
