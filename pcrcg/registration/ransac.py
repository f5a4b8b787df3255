"""RANSAC on putative correspondences: our batched implementation and Open3D's as reference.

Open3D 0.20's ``registration_ransac_based_on_correspondence`` (the code path of its
feature-matching RANSAC too) per iteration draws ``ransac_n`` = 3 correspondences with
replacement, fits a rigid transform (Umeyama without scale), rejects it when an edge of the
sample differs in length by more than 10 % between source and target
(``CorrespondenceCheckerBasedOnEdgeLength(0.9)``) or a sampled pair lies farther than the
distance threshold after the fit (``CorrespondenceCheckerBasedOnDistance``), and validates the
survivors: the hypothesis' *fitness* is the fraction of all source points with a target point
within the threshold (KD-tree search), ties broken by lower RMSE. When a hypothesis becomes the
best, the exit count is updated from its *correspondence* inlier ratio w:
``log(1 - confidence) / log(1 - w**ransac_n)``; the loop stops there or at ``max_iteration``.
The best hypothesis is returned as is (no refit on its inliers).

:func:`ransac` does the same, in batches:

* the edge-length check needs no transform, so it runs before the fit and most samples never
  reach the (batched, SVD) Kabsch solve;
* correspondence residuals of H hypotheses on all K correspondences are one (H, 17) x (17, K)
  matrix product, ``||R s + t - q||^2 = |s|^2 + |q|^2 + |t|^2 + 2 (R^T t).s - 2 t.q -
  2 vec(R).vec(q s^T)`` (coordinates centred first, so float32 is exact enough);
* ``score="overlap"`` (default, Open3D's and Predator's ranking) scores a batch's validated
  hypotheses with one KD-tree query; ``score="correspondences"`` ranks by inlier
  correspondences instead (classic RANSAC, Open3D's current master), which needs no search;
* early termination uses Open3D's formula, checked after each batch (batches start small and
  double, so easy pairs stop after a few hundred hypotheses, as Open3D does).

Everything runs in torch on the given ``device``. Sampling uses a NumPy generator seeded by the
caller, so a given seed gives the same result on every run. On CPU (``ransac(..., fast=True)``, the
default) the edge-length check runs in NumPy (one edge at a time, on the samples still standing: with
Open3D's early exit most of the ~50,000 draws of a hard pair are checked and fewer than 1 % pass), the
batches of 32 ... 4096 draws are checked in one call and their samples fitted at least 32 at a time
(:class:`_Hypotheses`), and the fit uses fewer tensor operations; all give what the torch path gives, bit for bit
(``fast=False``, the path of other devices, batch by batch).

Predator's numbers were produced with Open3D 0.10, whose feature-matching RANSAC matched a
source point's descriptor lazily inside the loop, scored by the same geometric fitness and
stopped after 1,000 validated hypotheses (``RANSACConvergenceCriteria(50000, 1000)``). In Open3D
>= 0.12 the second argument is a confidence, clamped to 1.0: the same call then runs all 50,000
iterations and validates every hypothesis that passes the checkers.

Both budgets are settings of :class:`RansacConfig` (:attr:`RansacConfig.budget` names them):

* Open3D 0.10, the budget behind Predator's and PCR-CG's published numbers (both pin
  ``open3d==0.10``): ``max_validation=1000, confidence=1.0``: stop after the 1,000th hypothesis that
  passes both checkers and is scored (or at ``max_iterations`` draws), no early termination;
* Open3D >= 0.12: ``max_validation=None`` and early termination at ``confidence`` (0.999 here;
  Open3D's formula), at most ``max_iterations`` draws.

The run config defaults to the first (``conf/registration/default.yaml``); ``registration=early_exit``
selects the second. The dataclass itself defaults to the second (the library's behaviour).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch

from pcrcg.device import torch_threads
from pcrcg.errors import ConfigError


@dataclass
class RansacConfig:
    """RANSAC settings (Predator's 3DMatch protocol by default).

    distance: inlier threshold and distance checker, metres. edge_length: similarity threshold of
    the edge-length checker. confidence: early termination (1.0 runs all ``max_iterations``).
    batch_size: hypotheses in the first batch (doubles up to ``max_batch``). refine: number of
    least-squares refits on the inliers of the best hypothesis (0 = Open3D's behaviour).
    dtype: ``float32`` or ``float64`` for hypothesis scoring. threads: torch CPU threads while
    RANSAC runs (0 = leave torch's setting). The batches are many small tensor operations, and
    with 2 threads on a busy 2-core machine torch's OpenMP regions ran 20-40x slower than with 1.
    score: ``overlap`` ranks hypotheses as Open3D 0.10-0.20 (and so Predator) do, by the fraction
    of all source points with a target point within ``distance``; ``correspondences`` by the
    number of inlier correspondences (classic RANSAC, and Open3D's current master).
    max_validation: stop once this many hypotheses have passed both checkers and been scored
    (Open3D 0.10's ``RANSACConvergenceCriteria(max_iteration, max_validation)``); None: no cap.
    prune: with ``score="overlap"`` on CPU, decide most points of a hypothesis with a voxel grid of the
    target instead of the KD-tree and skip hypotheses that can no longer win (:class:`_GridOverlapScore`:
    the same chosen hypothesis; ``False``: score every point of every hypothesis, the reference).
    prune_min_points: only where the grid would be too large (more than ``_GridOverlapScore.MAX_CELLS``
    cells of ``distance / 2``): the chunked shortcut (:class:`_PrunedOverlapScore`) from this many
    source points, the reference below. Measured (RANSAC alone, the Open3D 0.10 budget, 8 simulated pairs from the real
    redkitchen frames at 2.5 cm x 3 seeds, identical results): N = 5000 29.4 s (chunked) -> 8.0 s (grid),
    N = 1000 6.4 s (reference) -> 3.8 s, N = 250 2.0 s -> 1.6 s.
    """

    distance: float = 0.05
    ransac_n: int = 3
    edge_length: float = 0.9
    max_iterations: int = 50000
    confidence: float = 0.999
    batch_size: int = 32
    max_batch: int = 8192
    refine: int = 0
    dtype: str = "float32"
    threads: int = 1
    score: str = "overlap"
    max_validation: int | None = None
    prune: bool = True
    prune_min_points: int = 2000

    def __post_init__(self) -> None:
        if self.distance <= 0:
            raise ConfigError("ransac.distance", self.distance, "> 0 (metres)")
        if self.ransac_n < 3:
            raise ConfigError("ransac.ransac_n", self.ransac_n, ">= 3")
        if not 0.0 < self.edge_length <= 1.0:
            raise ConfigError("ransac.edge_length", self.edge_length, "in (0, 1]")
        if self.max_iterations < 1:
            raise ConfigError("ransac.max_iterations", self.max_iterations, ">= 1")
        if not 0.0 <= self.confidence <= 1.0:
            raise ConfigError("ransac.confidence", self.confidence, "in [0, 1]")
        if self.batch_size < 1 or self.max_batch < self.batch_size:
            raise ConfigError("ransac.batch_size", self.batch_size, ">= 1 and <= ransac.max_batch")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError("ransac.dtype", self.dtype, "float32 or float64")
        if self.score not in ("overlap", "correspondences"):
            raise ConfigError("ransac.score", self.score, "overlap | correspondences")
        if self.max_validation is not None and (isinstance(self.max_validation, bool) or int(self.max_validation) < 1):
            raise ConfigError("ransac.max_validation", self.max_validation, "an integer >= 1, or null (no cap)")

    @property
    def budget(self) -> str:
        """In words: which Open3D's RANSAC budget these settings reproduce."""
        if self.max_validation is not None:
            text = (f"Open3D 0.10 criteria ({self.max_iterations}, {self.max_validation}): stops after "
                    f"{self.max_validation} validated hypotheses or {self.max_iterations} draws")
            return text + ("" if self.confidence >= 1.0 else f", early exit at confidence {self.confidence}")
        if self.confidence < 1.0:
            return (f"Open3D >= 0.12: up to {self.max_iterations} draws, early exit at confidence "
                    f"{self.confidence}, no validation cap")
        return f"every one of {self.max_iterations} draws (Open3D >= 0.12 with confidence 1.0)"

    @classmethod
    def from_dict(cls, d) -> "RansacConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ConfigError("ransac", sorted(unknown), f"keys among {sorted(names)}")
        return cls(**{k: d[k] for k in d})


@dataclass
class RansacResult:
    """transform (4, 4) maps source into target; fitness = inliers / correspondences."""

    transform: np.ndarray
    fitness: float
    inlier_rmse: float
    n_inliers: int
    iterations: int
    n_checked: int = 0  # hypotheses that passed both checkers and were scored


def kabsch(src: torch.Tensor, tgt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares rigid fits ``R src + t ~ tgt`` for batches: src, tgt (B, n, 3) -> R (B, 3, 3), t (B, 3)."""
    cs, ct = src.mean(1, keepdim=True), tgt.mean(1, keepdim=True)
    H = (src - cs).transpose(1, 2) @ (tgt - ct)
    U, _, Vh = torch.linalg.svd(H)
    V = Vh.transpose(1, 2)
    d = torch.sign(torch.linalg.det(V @ U.transpose(1, 2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.ones(src.shape[0], 3, dtype=src.dtype, device=src.device)
    D[:, 2] = d
    R = (V * D[:, None, :]) @ U.transpose(1, 2)
    t = ct[:, 0] - (R @ cs[:, 0, :, None])[..., 0]
    return R, t


def kabsch_numpy(src: np.ndarray, tgt: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted least-squares rigid transform (4, 4) with ``T src ~ tgt``; src, tgt (n, 3) float64."""
    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    cs, ct = w @ src, w @ tgt
    H = (src - cs).T @ ((tgt - ct) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = ct - R @ cs
    return T


def _features(s: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """(K, 17) per-correspondence terms of the expanded squared residual (see module docstring)."""
    outer = (q[:, :, None] * s[:, None, :]).reshape(-1, 9)  # vec(q s^T), row-major (i, j) = q_i s_j
    const = (s * s).sum(1, keepdim=True) + (q * q).sum(1, keepdim=True)
    ones = torch.ones_like(const)
    return torch.cat([s, q, outer, const, ones], dim=1)


def _coefficients(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(H, 17) per-hypothesis coefficients matching :func:`_features`."""
    Rt_t = (R.transpose(1, 2) @ t[:, :, None])[..., 0]
    ones = torch.ones(R.shape[0], 1, dtype=R.dtype, device=R.device)
    tt = (t * t).sum(1, keepdim=True)
    return torch.cat([2.0 * Rt_t, -2.0 * t, -2.0 * R.reshape(-1, 9), ones, tt], dim=1)


def _score(R, t, feats, thr2, chunk_elems=1 << 22):
    """Inlier counts (H,) and summed squared inlier residuals (H,) of H hypotheses."""
    H, K = R.shape[0], feats.shape[0]
    coef = _coefficients(R, t)
    counts, errs = [], []
    step = max(1, chunk_elems // max(K, 1))
    for a in range(0, H, step):
        d2 = (coef[a : a + step] @ feats.T).clamp_min_(0.0)
        inl = d2 < thr2
        counts.append(inl.sum(1))
        errs.append(torch.where(inl, d2, torch.zeros_like(d2)).sum(1))
    return torch.cat(counts), torch.cat(errs)


class _OverlapScore:
    """Open3D's hypothesis score: how many of *all* source points have a target point within
    ``distance`` after the transform (KD-tree radius search), and their summed squared distances.

    CPU: one SciPy cKDTree query for a whole batch of hypotheses; other devices: chunked cdist.
    Coordinates are the centred ones of :func:`ransac`. This is the reference implementation
    (``RansacConfig(prune=False)``); :class:`_PrunedOverlapScore` gives the same choice faster.
    """

    def __init__(self, src: np.ndarray, tgt: np.ndarray, distance: float, dtype, device: torch.device):
        self.distance = distance
        self.device = device
        self.src = torch.as_tensor(src, dtype=dtype, device=device)
        if device.type == "cpu":
            from scipy.spatial import cKDTree

            self.tree = cKDTree(tgt)
            self.tgt = None
        else:
            self.tree = None
            self.tgt = torch.as_tensor(tgt, dtype=dtype, device=device)

    def score(self, R: torch.Tensor, t: torch.Tensor, floor: int = 0) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Counts (H,) and summed squared inlier distances (H,) of hypotheses R (H, 3, 3), t (H, 3) (squared
        distances None where the scorer gives them on request, :meth:`_GridOverlapScore.errors`)."""
        return self(R, t, floor)

    def __call__(self, R: torch.Tensor, t: torch.Tensor, floor: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        H, N = R.shape[0], self.src.shape[0]
        q = self.src[None] @ R.transpose(1, 2) + t[:, None, :]  # (H, N, 3)
        if self.tree is not None:
            d, _ = self.tree.query(q.reshape(-1, 3).double().numpy(), k=1, distance_upper_bound=self.distance)
            d = torch.as_tensor(d.reshape(H, N))
        else:
            parts = [torch.cdist(q[h : h + 1].reshape(-1, 3), self.tgt).min(1).values for h in range(H)]
            d = torch.stack(parts).reshape(H, N)
        inl = d < self.distance
        d2 = torch.where(inl, d * d, torch.zeros_like(d))
        return inl.sum(1).to(self.device), d2.sum(1).to(self.device)


def _unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(a, axis=0, return_counts=True)`` for a (n, 3), the same rows in the same (lexicographic)
    order, with one lexsort of the columns instead of a sort of a structured view (several times faster)."""
    s = a[np.lexsort(a.T[::-1])]
    new = np.ones(len(s), dtype=bool)
    np.any(s[1:] != s[:-1], axis=1, out=new[1:])
    start = np.flatnonzero(new)
    return s[start], np.diff(np.append(start, len(s)))


class _PrunedOverlapScore(_OverlapScore):
    """The same score with two exact shortcuts (CPU only; same counts for every hypothesis that can
    still be chosen, so the same chosen hypothesis):

    * repeated source points (N sampled *with replacement* from fewer points, Predator's script) are
      queried once and counted with their multiplicity; repeated target points are dropped from the tree;
    * bail-out: the source points are scored in chunks, in a fixed shuffled order, and a hypothesis
      stops being scored once even all its unscored points could not bring it level with ``floor``
      (the best count of earlier batches) or with another hypothesis' count so far. Such a
      hypothesis' final count is below a count that is reached, so RANSAC could never choose it; its
      returned count is -1.
    """

    # chunks of the points: more chunks drop a losing hypothesis earlier, fewer cost less Python per chunk. With the
    # grid's cells of distance / 6 (below), CPU s per pair for all five N on 8 + 8 cpu-profile pairs (2026-12-06,
    # beside two sweep jobs, three interleaved rounds): 1: 0.386, 2: 0.359-0.376, 3: 0.363-0.377, 4: 0.372,
    # 8: 0.392, 16: 0.447 at Open3D 0.10's budget; 3 against 8 at Open3D's early exit: 0.183 against 0.200
    CHUNKS = 3

    def __init__(self, src: np.ndarray, tgt: np.ndarray, distance: float, dtype, device: torch.device):
        from scipy.spatial import cKDTree

        self.distance = distance
        self.device = device
        uniq, counts = _unique_rows(np.asarray(src))
        order = np.random.default_rng(0).permutation(len(uniq))  # fixed: scoring order only
        self.src = torch.as_tensor(uniq[order], dtype=dtype, device=device)
        self.weight = counts[order].astype(np.int64)
        self.total = int(self.weight.sum())
        self.tree = cKDTree(_unique_rows(np.asarray(tgt))[0])
        self.tgt = None
        n = len(uniq)
        self.bounds = np.unique(np.linspace(0, n, min(self.CHUNKS, max(n, 1)) + 1).astype(int))
        self.after = self.total - np.concatenate([[0], np.cumsum(self.weight)])[self.bounds]  # weight left

    def __call__(self, R: torch.Tensor, t: torch.Tensor, floor: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        H = R.shape[0]
        count = np.zeros(H, np.int64)
        err = np.zeros(H, np.float64)
        active = np.arange(H)
        for c in range(len(self.bounds) - 1):
            a, b = int(self.bounds[c]), int(self.bounds[c + 1])
            sel = torch.as_tensor(active)
            q = self.src[None, a:b] @ R[sel].transpose(1, 2) + t[sel][:, None, :]  # (h, b - a, 3)
            d, _ = self.tree.query(q.reshape(-1, 3).double().numpy(), k=1, distance_upper_bound=self.distance)
            d = d.reshape(len(active), b - a)
            inl = d < self.distance
            w = self.weight[a:b]
            count[active] += (inl * w).sum(1)
            err[active] += (np.where(inl, d * d, 0.0) * w).sum(1)
            left = int(self.after[c + 1])
            if left == 0:
                break
            level = max(int(floor), int(count[active].max()))
            keep = count[active] + left >= level
            count[active[~keep]] = -1
            active = active[keep]
            if len(active) == 0:
                break
        return torch.as_tensor(count), torch.as_tensor(err)


class _GridOverlapScore(_PrunedOverlapScore):
    """The same choice as :class:`_OverlapScore`, most points decided by a voxel grid instead of the KD-tree
    (CPU only). Exact: a hypothesis that can still be chosen gets its exact count, and the hypotheses of
    the batch's top count their exact summed squared distances; a hypothesis that cannot win gets -1.

    The target's bounding box (grown by ``distance``) is cut into cubic cells of edge ``distance / 6``
    (coarser, down to ``distance / 2``, for a box too large for ``MAX_CELLS``); until ``FINE_AFTER``
    hypotheses have been scored, of ``distance / 5`` (fewer cells to mark, more points left to the KD-tree).
    Finer cells leave fewer points *maybe* and cost more to mark: on 8 + 8 cpu-profile pairs at the five N
    (a geometry-only checkpoint of the record, 2026-12-06, beside two sweep jobs, CPU s per pair for all N,
    three interleaved rounds), Open3D 0.10's budget took 0.452 s with cells of distance / 4 (/ 3 until
    ``FINE_AFTER``), 0.417 with / 6 (/ 5), 0.414 with / 7 (/ 5), 0.438 with / 8 (/ 6); Open3D's early exit
    0.208, 0.210 and 0.211 with / 4 (/ 3), / 6 (/ 5) and / 6 (/ 3). The chosen transforms were the same in all.
    A cell is *in* when a target point lies in a cell so near that every point of both cells is closer
    than ``distance`` (so every point of the cell is an inlier), *out* when no target point lies in a
    cell whose nearest point could be within ``distance`` (every point of the cell is an outlier), and
    *maybe* otherwise. A hypothesis' count lies between its *in* points and its *in* + *maybe* points:
    one whose upper bound is below the best lower bound (or ``floor``) is dropped without a query, and
    only the *maybe* points of the others go to the KD-tree, chunk by chunk until a hypothesis can no longer win
    (:meth:`_settle`). With target points about as far apart as
    ``distance`` (Predator's sampled N), most points of a good hypothesis are *in* and most of a bad
    one *out*. The grid is built once ``WARM`` hypotheses have been scored (until then the chunked scorer
    does it); 0, at the first batch, was faster than 16 at Open3D's early exit on the benchmark's pairs (the
    chunked scorer's KD-tree queries of the first 16 cost more than the grid). :func:`ransac` asks for counts
    alone (:meth:`counts`) and for squared distances (:meth:`errors`) only where its tie-break needs them;
    ``__call__`` gives both, the batch's best hypotheses' squared distances without their *out* points (they
    add nothing). :func:`_overlap_scorer` uses it where the grid has at most ``MAX_CELLS`` cells.
    """

    CELLS_PER_DISTANCE = 6
    COARSE_CELLS_PER_DISTANCE = 5  # until FINE_AFTER hypotheses have been scored
    FINE_AFTER = 128
    MAX_CELLS = 1 << 26  # 64 MiB of int8: a box of about 3.3 m a side in cells of 1/6 of Predator's 5 cm (larger: coarser)
    GROW = 0.5  # metres around the central 99 % of the target points, for a box too large for MAX_CELLS
    TOP = 8  # hypotheses counted exactly first, to raise the bar for the others
    WARM = 0  # hypotheses scored by the chunked scorer before the grid is built (16 was slower on the benchmark)
    WRITE = 1 << 15  # cells marked per NumPy write while building (one offset per write was slower for small N)

    @classmethod
    def _frame(cls, tgt: np.ndarray, distance: float, cells: int | None = None
               ) -> tuple[float, int, np.ndarray, np.ndarray, int] | None:
        """Cell edge, reach in cells, origin (3,), grid shape (3,) and band (cells) for target points tgt (M, 3):
        cells of ``distance / cells`` (``CELLS_PER_DISTANCE``), coarser (down to ``distance / 2``) where that grid
        would have more than ``MAX_CELLS`` cells. Where even that one would (a few target points far off, as
        bad depth gives), a grid of the box of the central 99 % of the target points (grown by up to ``GROW``):
        its outer ``band`` cells are *maybe* (:meth:`_build`); None where that one is too large too."""
        lo, hi = np.min(tgt, axis=0), np.max(tgt, axis=0)
        for band in (0, 1):
            if band:  # the box of the central 99 % of the target points (grown by up to GROW)
                q_lo, q_hi = np.quantile(tgt, [0.005, 0.995], axis=0)
                lo, hi = np.maximum(lo, q_lo - cls.GROW), np.minimum(hi, q_hi + cls.GROW)
            for k in range(cells or cls.CELLS_PER_DISTANCE, 1, -1):
                c = distance / k
                reach = k + 1
                # a border of cells farther than ``distance`` from every (kept) target point
                border = (2 * reach + 3) if band else (reach + 1)
                origin = lo - border * c
                dims = np.ceil((hi + border * c - origin) / c).astype(np.int64) + 1
                if int(np.prod(dims)) <= cls.MAX_CELLS:
                    return c, reach, origin, dims, (2 * reach + 2) * band
        return None

    @classmethod
    def fits(cls, tgt: np.ndarray, distance: float) -> bool:
        """Whether a grid of target points tgt (M, 3) has at most ``MAX_CELLS`` cells."""
        return cls._frame(np.asarray(tgt, dtype=np.float64), distance) is not None

    def __init__(self, src: np.ndarray, tgt: np.ndarray, distance: float, dtype, device: torch.device):
        super().__init__(src, tgt, distance, dtype, device)
        self.grid = None  # (cells,) int8, built at the first batch after WARM scored hypotheses
        self.scored = 0
        self._w: torch.Tensor | None = None  # the weights as :meth:`_bounds` multiplies them
        self.weight_f = self.weight.astype(np.float64)

    def _build(self, cells: int | None = None) -> None:
        """The grid of cell states in cells of ``distance / cells`` (``CELLS_PER_DISTANCE``, or coarser where
        that grid is too large), occupied cell by occupied cell (few large writes, each to nearby cells)."""
        distance = self.distance
        tgt_u = self.tree.data
        self.fine = cells is None
        c, reach, self.origin, self.dims, band = self._frame(tgt_u, distance, cells)
        self.cell = c
        self.strides = np.array([self.dims[1] * self.dims[2], self.dims[2], 1], dtype=np.int64)
        at = np.floor((tgt_u - self.origin) / c).astype(np.int64)
        if band:  # target points whose cells' reach leaves the grid are left out; the band covers their reach
            at = at[np.all((at > reach) & (at < self.dims - 1 - reach), axis=1)]
        occupied = np.unique(at @ self.strides)
        r = np.arange(-reach, reach + 1)
        off = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
        # a cell pair whose nearest points are within ``distance`` / whose farthest points are nearer than it
        near = np.linalg.norm(np.maximum(np.abs(off) - 1, 0), axis=1) * c <= distance * (1 + 1e-3)
        sure = np.linalg.norm(np.abs(off) + 1, axis=1) * c < distance * (1 - 1e-3)
        grid = np.zeros(int(np.prod(self.dims)), dtype=np.int8)
        if band:  # cells within reach of the target points left out, and the border (points off the grid): maybe
            inner = grid.reshape(tuple(self.dims))
            inner[...] = 1
            inner[band:-band, band:-band, band:-band] = 0
        for label, offsets in ((1, off[near & ~sure]), (2, off[sure])):  # maybe, then in
            flat = np.sort(offsets @ self.strides)
            step = max(1, self.WRITE // len(flat))  # occupied cells per write
            for a in range(0, len(occupied), step):
                grid[(occupied[a : a + step, None] + flat).ravel()] = label
        self.grid = grid
        self.src_t = np.ascontiguousarray(self.src.numpy().T)  # (3, n) float32 or float64

    def _states(self, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """(H, n) int8 cell states of the transformed points: 0 out, 1 maybe, 2 in. The cell coordinates
        come from one matrix product, ``(R / cell) src + (t - origin) / cell``, which rounds a little
        differently from the scored points (well under a micrometre): the margin of the cell classes covers
        it. Points off the grid land on its border, whose cells are all *out*."""
        H, scale = R.shape[0], 1.0 / self.cell
        Rn, tn = R.numpy(), t.numpy()
        g = (Rn * Rn.dtype.type(scale)).reshape(3 * H, 3) @ self.src_t  # (3H, n): [(h, i), p] = (R_h p)_i / cell
        g = torch.from_numpy(g).view(H, 3, -1)
        # the elementwise passes in torch, the cells in int32 (the grid has at most MAX_CELLS < 2**31 cells): the
        # same IEEE operations as NumPy's, a third less time (less memory traffic than NumPy's int64 temporaries)
        g += torch.from_numpy(((tn - self.origin.astype(tn.dtype)) * tn.dtype.type(scale))[:, :, None])
        top = torch.from_numpy((self.dims - 1).astype(Rn.dtype))[:, None]
        g.clamp_(min=torch.zeros_like(top), max=top)
        cells = g.to(torch.int32)  # floor: g >= 0
        flat = cells[:, 0] * int(self.strides[0])
        flat.add_(cells[:, 1], alpha=int(self.strides[1])).add_(cells[:, 2])
        return torch.from_numpy(self.grid.take(flat.numpy()))

    def _query(self, R: torch.Tensor, t: torch.Tensor, group: np.ndarray, pts_of: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """KD-tree distances of the points marked in ``pts_of`` (g, n) bool under hypotheses ``group`` (g,):
        each marked point's hypothesis (m,) (a place in ``group``), point (m,) and distance (m,) (inf beyond
        ``distance``), hypothesis by hypothesis in point order. The points are transformed as the reference
        scorer transforms them."""
        sel = torch.as_tensor(group)
        q = (self.src[None] @ R[sel].transpose(1, 2) + t[sel][:, None, :]).numpy()  # (g, n, 3)
        hyp, pts = np.nonzero(pts_of)
        d, _ = self.tree.query(q[hyp, pts].astype(np.float64), k=1, distance_upper_bound=self.distance)
        return hyp, pts, d

    def counts(self, R: torch.Tensor, t: torch.Tensor, floor: int = 0) -> torch.Tensor:
        """(H,) int64: the exact count of every hypothesis of R (H, 3, 3), t (H, 3) that can still be chosen
        (reach ``floor`` and the batch's best count), -1 for the others."""
        if self.grid is None or (not self.fine and self.scored > self.FINE_AFTER):
            self._build(None if self.scored > self.FINE_AFTER else self.COARSE_CELLS_PER_DISTANCE)
        states = self._states(R, t)
        low, high = self._bounds(states)
        states = states.numpy()
        count = np.full(R.shape[0], -1, dtype=np.int64)
        level = max(int(floor), int(low.max()))
        order = np.argsort(-high, kind="stable")
        todo = order[high[order] >= level]
        for group in (todo[: self.TOP], todo[self.TOP :]):
            group = group[high[group] >= level]  # the bar may have risen
            if len(group) == 0:
                continue
            count[group] = self._settle(R, t, group, states[group] == 1, low[group], high[group], level)
            level = max(level, int(count[group].max()))
        count[(count >= 0) & (count < level)] = -1  # cannot be chosen
        return torch.from_numpy(count)

    def _bounds(self, states: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Weights (H,) int64 of the *in* points and of the *in* + *maybe* points of states (H, n) int8 (0, 1, 2):
        with s the states, ``s . w = maybe + 2 in`` and ``s^2 . w = maybe + 4 in``, two float32 products whose
        every partial sum is an integer below 2**24 (so exact in any order) while the weights sum to less than
        2**22; float64 above that."""
        dtype = torch.float32 if 4 * self.total < (1 << 24) else torch.float64
        if self._w is None or self._w.dtype != dtype:
            self._w = torch.from_numpy(self.weight_f).to(dtype)
        s = states.to(dtype)
        s1 = s @ self._w
        s2 = s.mul_(s) @ self._w
        inside = ((s2 - s1) / 2).round().to(torch.int64)
        return inside.numpy(), (s1.round().to(torch.int64) - inside).numpy()

    def _settle(self, R: torch.Tensor, t: torch.Tensor, group: np.ndarray, maybe: np.ndarray, low: np.ndarray,
                high: np.ndarray, level: int) -> np.ndarray:
        """Exact counts (g,) of hypotheses ``group`` (g,) whose *in* points weigh ``low`` (g,) and *in* + *maybe*
        points ``high`` (g,) (:meth:`_bounds`), their *maybe* points ``maybe`` (g, n) bool decided by the KD-tree
        chunk by chunk (the chunks of :class:`_PrunedOverlapScore`, in its shuffled point order); -1 for a
        hypothesis dropped on the way, once even all its undecided points could not bring it level with ``level`` (a count that is reached). Most
        queried hypotheses lose: on 12 pairs of the cpu profile at the five N, 96% of the *maybe* points that
        were queried all at once belonged to hypotheses that could not be chosen; in 8 chunks half as many
        points were queried (3.5M against 6.9M, cells of distance / 4). The points are transformed as the reference scorer transforms
        them, a chunk at a time."""
        count = low.astype(np.int64)
        left = high - low  # weight of the points not yet decided
        active = np.arange(len(group))
        for c in range(len(self.bounds) - 1):
            a, b = int(self.bounds[c]), int(self.bounds[c + 1])
            hyp, pts = np.nonzero(maybe[active, a:b])
            if len(hyp):
                sel = torch.as_tensor(group[active])
                q = (self.src[None, a:b] @ R[sel].transpose(1, 2) + t[sel][:, None, :]).numpy()  # (h, b - a, 3)
                d, _ = self.tree.query(q[hyp, pts].astype(np.float64), k=1, distance_upper_bound=self.distance)
                w = self.weight_f[a + pts]
                count[active] += np.bincount(hyp, weights=w * (d < self.distance), minlength=len(active)).astype(np.int64)
                left[active] -= np.bincount(hyp, weights=w, minlength=len(active)).astype(np.int64)
            active = active[count[active] + left[active] >= level]
            if len(active) == 0:
                break
        out = np.full(len(group), -1, dtype=np.int64)
        out[active] = count[active]
        return out

    def errors(self, R: torch.Tensor, t: torch.Tensor, top: np.ndarray) -> np.ndarray:
        """Summed weighted squared inlier distances (k,) of hypotheses top (k,), the reference's sums bit for
        bit: KD-tree distances of their *in* and *maybe* points, nothing for their *out* points (no inliers;
        adding 0.0 leaves a sum unchanged), point by point in point order (np.bincount adds in order, as the
        reference's sum does)."""
        if self.grid is None:
            self._build()
        top = np.asarray(top)
        hyp, pts, d = self._query(R, t, top, self._states(R[torch.as_tensor(top)], t[torch.as_tensor(top)]).numpy() > 0)
        inl = d < self.distance
        return np.bincount(hyp, weights=np.where(inl, d * d, 0.0) * self.weight[pts], minlength=len(top))

    def score(self, R: torch.Tensor, t: torch.Tensor, floor: int = 0) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`counts` (H,) and None (ask :meth:`errors`) once the grid is built; until then (``WARM``) the
        chunked scorer's counts and squared distances."""
        self.scored += R.shape[0]
        if self.grid is None and self.scored <= self.WARM:
            return super().__call__(R, t, floor)
        return self.counts(R, t, floor), None

    def __call__(self, R: torch.Tensor, t: torch.Tensor, floor: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """Counts (H,) as :meth:`counts` and summed squared distances (H,) of the batch's best hypotheses
        (0 for the others)."""
        count = self.counts(R, t, floor)
        err = np.zeros(R.shape[0], dtype=np.float64)
        best = int(count.max())
        if best >= 0:  # the RMSE tie-break needs the batch's best hypotheses' squared distances
            top = np.nonzero(count.numpy() == best)[0]
            err[top] = self.errors(R, t, top)
        return count, torch.from_numpy(err)


def _overlap_scorer(src: np.ndarray, tgt: np.ndarray, cfg: RansacConfig, dtype, dev: torch.device) -> _OverlapScore:
    """The overlap scorer for centred source (N, 3) and target (M, 3) points: with ``cfg.prune`` on CPU the
    grid scorer (or, for a grid too large, the chunked one from ``prune_min_points`` source points), else
    the reference. All give the same choice."""
    if not (cfg.prune and dev.type == "cpu"):
        return _OverlapScore(src, tgt, cfg.distance, dtype, dev)
    if _GridOverlapScore.fits(tgt, cfg.distance):
        return _GridOverlapScore(src, tgt, cfg.distance, dtype, dev)
    scorer = _PrunedOverlapScore if len(src) >= cfg.prune_min_points else _OverlapScore
    return scorer(src, tgt, cfg.distance, dtype, dev)


def _edge_pairs(n: int) -> tuple[list[int], list[int]]:
    a, b = zip(*[(i, j) for i in range(n) for j in range(i + 1, n)])
    return list(a), list(b)


def _identity_result(iterations: int = 0) -> RansacResult:
    return RansacResult(np.eye(4), 0.0, 0.0, 0, iterations)


def ransac(
    src_points: np.ndarray,
    tgt_points: np.ndarray,
    correspondences: np.ndarray,
    cfg: RansacConfig | None = None,
    seed: int | np.random.Generator = 0,
    device: str | torch.device | None = None,
    *,
    fast: bool = True,
) -> RansacResult:
    """Batched RANSAC: transform mapping source into target from putative correspondences.

    src_points (N, 3), tgt_points (M, 3); correspondences (K, 2) int: rows (source index,
    target index). Returns the identity with fitness 0 when K < ransac_n or no hypothesis passes.
    fast: on CPU, the edge-length checks in NumPy and the leaner fit of :func:`_fit_and_check_distance_cpu`
    (False: the torch path of other devices, the reference; both give the same result bit for bit).
    """
    cfg = cfg or RansacConfig()
    with torch_threads(cfg.threads, device), torch.no_grad():
        return _ransac(src_points, tgt_points, correspondences, cfg, seed, device, fast)


def _ransac(src_points, tgt_points, correspondences, cfg, seed, device, fast: bool = True) -> RansacResult:
    corr = np.asarray(correspondences, dtype=np.int64).reshape(-1, 2)
    K, n = len(corr), cfg.ransac_n
    if K < n:
        return _identity_result()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    dev = torch.device(device) if device is not None else torch.device("cpu")
    dtype = torch.float32 if cfg.dtype == "float32" else torch.float64

    s64 = np.asarray(src_points, dtype=np.float64)[corr[:, 0]]
    q64 = np.asarray(tgt_points, dtype=np.float64)[corr[:, 1]]
    cs, cq = s64.mean(0), q64.mean(0)  # centre both sides; undone at the end
    S = torch.as_tensor(s64 - cs, dtype=dtype, device=dev)
    Q = torch.as_tensor(q64 - cq, dtype=dtype, device=dev)
    feats = _features(S, Q)
    thr2 = cfg.distance**2
    use_numpy = bool(fast) and dev.type == "cpu"
    edges = _EdgeCheck(S, Q, n, cfg.edge_length**2, use_numpy)
    fit = _fit_and_check_distance_cpu if use_numpy else _fit_and_check_distance
    overlap = None
    if cfg.score == "overlap":
        overlap = _overlap_scorer(np.asarray(src_points, dtype=np.float64) - cs,
                                  np.asarray(tgt_points, dtype=np.float64) - cq, cfg, dtype, dev)

    best = _Best(getattr(overlap, "errors", None))
    draws = _Hypotheses(rng, K, n, edges, lambda idx: fit(S[idx], Q[idx], cfg.distance), cfg.batch_size,
                        cfg.max_batch, _Hypotheses.WINDOW if use_numpy else 0, isinstance(seed, np.random.Generator))
    limit, drawn, n_checked = cfg.max_iterations, 0, 0
    log_fail = math.log(1.0 - cfg.confidence) if cfg.confidence < 1.0 else -math.inf
    while drawn < limit:
        b, R, t, pos = draws.next(limit - drawn)  # pos: each hypothesis' place in the batch (draw order)
        drawn += b
        if R.shape[0] == 0:
            continue
        if cfg.max_validation is not None and n_checked + R.shape[0] >= cfg.max_validation:
            # Open3D 0.10: the max_validation-th validated hypothesis is the last one scored
            keep = int(cfg.max_validation) - n_checked
            R, t = R[:keep], t[:keep]
            drawn -= b - (int(pos[keep - 1]) + 1)  # the draws up to and including it
            limit = drawn
        n_checked += R.shape[0]
        if overlap is not None:  # ranked by overlap; correspondence inliers only for the exit rule of a new best
            count, err2 = overlap.score(R, t, best.count)
        else:
            count, err2 = _score(R, t, feats, thr2)
        k = best.offer(R, t, count, err2)
        if k is not None:
            n_corr = int(count[k]) if overlap is None else int(_score(R[k : k + 1], t[k : k + 1], feats, thr2)[0][0])
            w = n_corr / K  # Open3D's exit rule uses the correspondence inlier ratio
            if cfg.confidence < 1.0:
                exit_itr = 0.0 if w >= 1.0 else log_fail / math.log(1.0 - w**n)
                if exit_itr < cfg.max_iterations:
                    limit = min(limit, int(math.ceil(exit_itr)))
    draws.finish()
    if best.R is None:
        return _identity_result(drawn)

    best_R, best_t = best.R[0].double().cpu().numpy(), best.t[0].double().cpu().numpy()
    T = np.eye(4)
    T[:3, :3] = best_R
    T[:3, 3] = best_t + cq - best_R @ cs  # undo the centring
    T = _refine(T, s64, q64, cfg.distance, cfg.refine, n)
    out = _evaluate(T, s64, q64, cfg.distance, drawn)
    out.n_checked = n_checked
    return out


class _Hypotheses:
    """The hypotheses of successive batches of draws (``batch`` draws, doubling up to ``max_batch``): samples
    idx (b, n) of K correspondences drawn with ``rng``, edge-checked (``check``: :class:`_EdgeCheck`) a window
    of batches at a time (up to ``window`` draws) and fitted and distance-checked (``fit``: idx (m, n) -> R
    (m, 3, 3), t (m, 3), ok (m,)) at least ``FIT`` edge-checked samples at a time (fewer, larger calls; a
    sample's checks and fit do not depend on the others), handed out batch by batch. The draws are those of one
    batch at a time (NumPy draws the same numbers in one call as in several); ``finish`` puts a caller's
    generator where drawing batch by batch would have left it."""

    WINDOW = 8192  # the batches of 32 ... 4096 draws edge-checked together
    FIT = 32  # samples fitted together at least (an easy pair stops after a few dozen hypotheses)

    def __init__(self, rng: np.random.Generator, K: int, n: int, check, fit, batch: int, max_batch: int,
                 window: int, callers_rng: bool):
        self.rng, self.K, self.n, self.check, self.fit = rng, K, n, check, fit
        self.batch, self.max_batch, self.window, self.callers_rng = batch, max_batch, window, callers_rng
        self.rows = self.cursor = 0  # draws in the window, draws of it handed out

    def next(self, left: int) -> tuple[int, torch.Tensor, torch.Tensor, np.ndarray]:
        """The next batch, of at most ``left`` draws: its size b, its hypotheses that pass both checkers R (h, 3, 3),
        t (h, 3) and their places in the batch (h,) int64, in draw order."""
        b = min(self.batch, left)
        self.batch = min(2 * self.batch, self.max_batch)
        if self.cursor == self.rows:
            self._draw(b, left)
        a = self.cursor
        self.cursor += b
        lo, hi = np.searchsorted(self.pos, [a, a + b])
        if hi > self.fitted:  # fit this batch's samples and at least FIT in all
            end = min(len(self.pos), max(hi, self.fitted + (self.FIT if self.window else 0)))
            done = slice(self.fitted, end)
            self.R[done], self.t[done], self.ok[done] = self.fit(self.idx[done])
            self.fitted = end
        ok = self.ok[lo:hi]
        return b, self.R[lo:hi][ok], self.t[lo:hi][ok], self.pos[lo:hi][ok.cpu().numpy()] - a

    def _draw(self, b: int, left: int) -> None:
        """Draws and edge-checks the next window: a batch of b draws and the whole batches after it within
        ``window`` draws and ``left``."""
        rows, size, left = b, self.batch, left - b
        while left > 0 and rows + min(size, left) <= self.window:
            rows, left = rows + min(size, left), left - min(size, left)
            size = min(2 * size, self.max_batch)
        if self.callers_rng:
            self.state = self.rng.bit_generator.state
        self.idx, pos = self.check(self.rng.integers(0, self.K, size=(rows, self.n)))
        self.pos = pos.cpu().numpy()
        self.rows, self.cursor, self.fitted = rows, 0, 0
        S = self.check.S
        self.R = torch.empty(len(self.pos), 3, 3, dtype=S.dtype, device=S.device)
        self.t = torch.empty(len(self.pos), 3, dtype=S.dtype, device=S.device)
        self.ok = torch.empty(len(self.pos), dtype=torch.bool, device=S.device)

    def finish(self) -> None:
        """Rewinds a caller's generator to just after the draws handed out."""
        if self.callers_rng and self.cursor < self.rows:
            self.rng.bit_generator.state = self.state
            self.rng.integers(0, self.K, size=(self.cursor, self.n))


class _Best:
    """The best hypothesis so far: its count, R (1, 3, 3), t (1, 3) and squared RMSE, the last computed only
    where a tie needs it (``errors``: the scorer's :meth:`_GridOverlapScore.errors`, for scorers that give
    counts alone)."""

    def __init__(self, errors=None):
        self.count, self._err2, self.R, self.t = 0, math.inf, None, None
        self.errors = errors

    def err2(self) -> float:
        if self._err2 is None:
            self._err2 = float(self.errors(self.R, self.t, np.zeros(1, dtype=np.int64))[0] / self.count)
        return self._err2

    def offer(self, R: torch.Tensor, t: torch.Tensor, count: torch.Tensor, err2: torch.Tensor | None) -> int | None:
        """A batch's hypotheses R (H, 3, 3), t (H, 3) with their counts (H,) and summed squared distances (H,)
        (None: ask ``errors`` where needed). Its best (most inliers, then lowest RMSE, then first) replaces the
        best so far if it has more inliers, or as many with a lower RMSE: its place in the batch, else None."""
        cmax = int(count.max())
        if cmax <= 0:
            return None
        if err2 is None:
            top = np.flatnonzero(count.numpy() == cmax)
            if len(top) == 1 and cmax > self.count:  # no tie to break: its squared distances can wait
                return self._take(R, t, int(top[0]), cmax, None)
            err2 = torch.zeros(len(count), dtype=torch.float64)
            err2[torch.from_numpy(top)] = torch.from_numpy(self.errors(R, t, top))
        rmse2 = torch.where(count == cmax, err2 / cmax, torch.full_like(err2, math.inf))
        k = int(torch.argmin(rmse2))
        r2 = float(rmse2[k])
        if cmax > self.count or (cmax == self.count and r2 < self.err2()):
            return self._take(R, t, k, cmax, r2)
        return None

    def _take(self, R: torch.Tensor, t: torch.Tensor, k: int, count: int, err2: float | None) -> int:
        self.count, self._err2, self.R, self.t = count, err2, R[k : k + 1], t[k : k + 1]
        return k


class _EdgeCheck:
    """Open3D's edge-length checker on samples of the centred correspondences S, Q (K, 3), before any fit.

    With ``use_numpy`` (the CPU default) it runs in NumPy on the same float32 / float64 values with the
    same operations in the same order, so the same samples pass as with :func:`_edge_length_ok` (torch,
    the path on other devices): the batches are large (up to ``max_batch`` samples) and almost all fail,
    so it checks one edge at a time on the samples still standing.
    """

    def __init__(self, S: torch.Tensor, Q: torch.Tensor, n: int, sim2: float, use_numpy: bool):
        self.S, self.Q, self.sim2, self.use_numpy = S, Q, sim2, use_numpy
        self.ea, self.eb = _edge_pairs(n)
        if use_numpy:  # coordinate columns (3 x (K,)): np.take on a 1-D array is NumPy's fastest gather
            self.s_cols = [np.ascontiguousarray(S[:, c].numpy()) for c in range(3)]
            self.q_cols = [np.ascontiguousarray(Q[:, c].numpy()) for c in range(3)]

    def __call__(self, idx: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Samples idx (b, n) int64 -> the passing samples (m, n) and their places in the batch (m,), torch on
        the device of S."""
        if not self.use_numpy:
            idx_t = torch.as_tensor(idx, device=self.S.device)
            ok = _edge_length_ok(self.S, self.Q, idx_t, self.ea, self.eb, self.sim2)
            return idx_t[ok], torch.nonzero(ok).reshape(-1)
        pos = np.arange(len(idx))
        for a, c in zip(self.ea, self.eb):  # the same test as _edge_length_ok, one edge at a time
            ia, ic = idx[:, a], idx[:, c]
            ls, lq = _squared_lengths(self.s_cols, ia, ic), _squared_lengths(self.q_cols, ia, ic)
            ok = (ls >= lq * self.sim2) & (lq >= ls * self.sim2)
            pos, idx = pos[ok], idx[ok]
            if len(pos) == 0:
                break
        return torch.from_numpy(idx), torch.from_numpy(pos)


def _squared_lengths(cols: list[np.ndarray], ia: np.ndarray, ic: np.ndarray) -> np.ndarray:
    """|p[ia] - p[ic]|^2 (b,) of points given as coordinate columns cols (3 x (K,)), summed x, y, z in
    this order as torch's ``(e * e).sum(1)`` does (bit for bit)."""
    out = None
    for col in cols:
        e = col.take(ia) - col.take(ic)
        out = e * e if out is None else out + e * e
    return out


def _edge_length_ok(S: torch.Tensor, Q: torch.Tensor, idx: torch.Tensor, ea, eb, sim2: float) -> torch.Tensor:
    """Open3D's edge-length checker on samples idx (b, n) of centred correspondences S, Q (K, 3):
    (b,) bool. On squared lengths; it needs no transform, so it runs before the fit."""
    ok = torch.ones(idx.shape[0], dtype=torch.bool, device=idx.device)
    for a, c in zip(ea, eb):
        es = S[idx[:, a]] - S[idx[:, c]]
        eq = Q[idx[:, a]] - Q[idx[:, c]]
        ls, lq = (es * es).sum(1), (eq * eq).sum(1)
        ok &= (ls >= lq * sim2) & (lq >= ls * sim2)
    return ok


def _fit_and_check_distance(ps: torch.Tensor, pq: torch.Tensor, distance: float):
    """Kabsch fits of samples ps, pq (h, n, 3) and Open3D's distance checker: R (h, 3, 3), t (h, 3),
    ok (h,) bool (every sampled pair within ``distance`` after the fit)."""
    R, t = kabsch(ps, pq)
    res = (ps @ R.transpose(1, 2) + t[:, None, :] - pq).norm(dim=-1)
    return R, t, (res <= distance).all(1)


def _fit_and_check_distance_cpu(ps: torch.Tensor, pq: torch.Tensor, distance: float):
    """:func:`_fit_and_check_distance` bit for bit with fewer tensor operations (CPU tensors): the same
    products in the same order (ATen's small-matrix bmm), the reflection's sign from NumPy's determinants of
    U and V^T (their product's sign is that of det(V U^T), a rotation's or a reflection's, +-1), and V^T's
    last row flipped in place instead of a (h, 3) matrix of signs."""
    cs, ct = ps.mean(1, keepdim=True), pq.mean(1, keepdim=True)
    U, _, Vh = torch.linalg.svd((ps - cs).transpose(1, 2) @ (pq - ct))
    sign = np.sign(np.linalg.det(U.numpy()) * np.linalg.det(Vh.numpy()))
    sign[sign == 0] = 1.0
    Vh[:, 2] *= torch.from_numpy(sign)[:, None]
    R = Vh.transpose(1, 2) @ U.transpose(1, 2)  # (V D) U^T
    t = ct[:, 0] - (R @ cs[:, 0, :, None])[..., 0]
    res = (ps @ R.transpose(1, 2) + t[:, None, :] - pq).norm(dim=-1)
    return R, t, (res <= distance).all(1)


def _refine(T: np.ndarray, src_c: np.ndarray, tgt_c: np.ndarray, distance: float, rounds: int, n: int) -> np.ndarray:
    """Up to ``rounds`` least-squares refits of T (4, 4) on its inlier correspondences (K, 3), kept
    only while they do not lose inliers (0 rounds: Open3D's behaviour, T as is)."""
    for _ in range(rounds):
        res = np.linalg.norm(src_c @ T[:3, :3].T + T[:3, 3] - tgt_c, axis=1)
        inl = res < distance
        if inl.sum() < n:
            break
        T_new = kabsch_numpy(src_c[inl], tgt_c[inl])
        res_new = np.linalg.norm(src_c @ T_new[:3, :3].T + T_new[:3, 3] - tgt_c, axis=1)
        if (res_new < distance).sum() < inl.sum():
            break
        T = T_new
    return T


# --------------------------------------------------------------------------- Open3D reference


def _o3d_cloud(points: np.ndarray):
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))


def _o3d_checkers(cfg: RansacConfig):
    import open3d as o3d

    reg = o3d.pipelines.registration
    return [reg.CorrespondenceCheckerBasedOnEdgeLength(cfg.edge_length), reg.CorrespondenceCheckerBasedOnDistance(cfg.distance)]


def _evaluate(T: np.ndarray, src_c: np.ndarray, tgt_c: np.ndarray, distance: float, iterations: int) -> RansacResult:
    """RansacResult of transform T (4, 4) on corresponding points src_c, tgt_c (K, 3)."""
    res = np.linalg.norm(src_c @ T[:3, :3].T + T[:3, 3] - tgt_c, axis=1)
    inl = res < distance
    n_inl = int(inl.sum())
    rmse = float(np.sqrt(np.mean(res[inl] ** 2))) if n_inl else 0.0
    return RansacResult(T, n_inl / max(len(res), 1), rmse, n_inl, iterations)


def _from_o3d(res, src_c: np.ndarray, tgt_c: np.ndarray, distance: float) -> RansacResult:
    # Open3D reports the geometric overlap as fitness; ours report correspondence inliers.
    return _evaluate(np.asarray(res.transformation, dtype=np.float64).copy(), src_c, tgt_c, distance, -1)


def _no_validation_cap(cfg: RansacConfig) -> None:
    """The installed Open3D (>= 0.12) has no validation budget: refuse one rather than ignore it."""
    if cfg.max_validation is not None:
        raise ConfigError("ransac.max_validation", cfg.max_validation,
                          "null with Open3D's own RANSAC (registration.backend=open3d): Open3D >= 0.12 has no "
                          "validation budget; the torch backend reproduces Open3D 0.10's")


def ransac_open3d(
    src_points: np.ndarray,
    tgt_points: np.ndarray,
    correspondences: np.ndarray,
    cfg: RansacConfig | None = None,
    seed: int | None = 0,
) -> RansacResult:
    """Open3D's ``registration_ransac_based_on_correspondence`` with the same settings.

    Seeded through ``open3d.utility.random.seed``; with more than one OpenMP thread its result
    still depends on thread scheduling.
    """
    import open3d as o3d

    cfg = cfg or RansacConfig()
    _no_validation_cap(cfg)
    reg = o3d.pipelines.registration
    corr = np.asarray(correspondences, dtype=np.int32).reshape(-1, 2)
    if len(corr) < cfg.ransac_n:
        return _identity_result()
    if seed is not None:
        o3d.utility.random.seed(int(seed))
    res = reg.registration_ransac_based_on_correspondence(
        _o3d_cloud(src_points),
        _o3d_cloud(tgt_points),
        o3d.utility.Vector2iVector(corr),
        cfg.distance,
        reg.TransformationEstimationPointToPoint(False),
        cfg.ransac_n,
        _o3d_checkers(cfg),
        reg.RANSACConvergenceCriteria(cfg.max_iterations, cfg.confidence),
    )
    corr = corr.astype(np.int64)
    return _from_o3d(res, np.asarray(src_points, np.float64)[corr[:, 0]], np.asarray(tgt_points, np.float64)[corr[:, 1]], cfg.distance)


def ransac_feature_matching_open3d(
    src_points: np.ndarray,
    tgt_points: np.ndarray,
    src_desc: np.ndarray,
    tgt_desc: np.ndarray,
    cfg: RansacConfig | None = None,
    mutual: bool = False,
    seed: int | None = 0,
) -> RansacResult:
    """Open3D's ``registration_ransac_based_on_feature_matching`` (KD-tree matching + RANSAC).

    This is Predator's registration call ported to Open3D 0.20; pass
    ``RansacConfig(confidence=1.0)`` to reproduce its ``RANSACConvergenceCriteria(50000, 1000)``
    (the 1000 is clamped to a confidence of 1.0: no early termination).
    """
    import open3d as o3d

    cfg = cfg or RansacConfig()
    _no_validation_cap(cfg)
    reg = o3d.pipelines.registration
    if seed is not None:
        o3d.utility.random.seed(int(seed))
    fs, ft = reg.Feature(), reg.Feature()
    fs.data = np.asarray(src_desc, dtype=np.float64).T
    ft.data = np.asarray(tgt_desc, dtype=np.float64).T
    res = reg.registration_ransac_based_on_feature_matching(
        _o3d_cloud(src_points),
        _o3d_cloud(tgt_points),
        fs,
        ft,
        bool(mutual),
        cfg.distance,
        reg.TransformationEstimationPointToPoint(False),
        cfg.ransac_n,
        _o3d_checkers(cfg),
        reg.RANSACConvergenceCriteria(cfg.max_iterations, cfg.confidence),
    )
    T = np.asarray(res.transformation, dtype=np.float64).copy()
    return RansacResult(T, float(res.fitness), float(res.inlier_rmse), len(res.correspondence_set), -1)
