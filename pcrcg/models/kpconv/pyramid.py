"""Multi-level KPConv inputs, precomputed on the CPU in the data pipeline.

Level 0 is the fragment grid-subsampled at ``voxel``; level l at ``voxel * 2**l``. At level l the
convolution radius is ``voxel * conv_radius * 2**l``. Per level we keep

* ``neighbors[l]`` (N_l, H): conv neighbours within the level (radius r_l),
* ``pools[l]`` (N_{l+1}, H): neighbours in level l of each level-(l+1) point (radius r_l),
* ``upsamples[l]`` (N_l, 1): the nearest level-(l+1) point of each level-l point,

all padded with the shadow index (the number of support points) and truncated to
``limits[l]`` neighbours, nearest first.

Neighbourhoods depend only on distances, so they are invariant to rigid motions: a fragment's
pyramid is built once in its own frame (and cached, :class:`PyramidCache`), then moved with
:meth:`FragmentPyramid.transformed` for augmentation. Two fragments are stacked into a pair with
:func:`stack_pair` (source first).
"""

from __future__ import annotations

import hashlib
import os
import secrets
import warnings
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Hashable, Iterable, Sequence

import numpy as np
import torch

from pcrcg.models.kpconv.ops import grid_subsample, nearest_neighbor, neighbor_counts, radius_neighbors, support_tree


@dataclass(frozen=True)
class PyramidSpec:
    """Sizes of the pyramid. ``limits`` (one per level) caps the neighbours per point."""

    voxel: float
    num_layers: int
    conv_radius: float = 2.5
    limits: tuple[int, ...] = ()
    max_points: int = 30000

    def radius(self, layer: int) -> float:
        return self.voxel * self.conv_radius * 2**layer

    def cell(self, layer: int) -> float:
        return self.voxel * 2**layer

    def limit(self, layer: int) -> int:
        if not self.limits:
            return 64
        return int(self.limits[min(layer, len(self.limits) - 1)])

    def key(self) -> tuple:
        return (round(self.voxel, 9), self.num_layers, round(self.conv_radius, 9), tuple(self.limits), self.max_points)


@dataclass
class FragmentPyramid:
    """NumPy pyramid of one fragment (see module docstring for shapes; indices int32)."""

    points: list[np.ndarray]
    neighbors: list[np.ndarray]
    pools: list[np.ndarray]
    upsamples: list[np.ndarray]

    @property
    def num_layers(self) -> int:
        return len(self.points)

    def transformed(self, T: np.ndarray) -> "FragmentPyramid":
        """The same pyramid after the rigid 4x4 ``T`` (indices unchanged: they are rotation invariant)."""
        R, t = np.asarray(T)[:3, :3], np.asarray(T)[:3, 3]
        pts = [(p.astype(np.float64) @ R.T + t).astype(np.float32) for p in self.points]
        return FragmentPyramid(pts, self.neighbors, self.pools, self.upsamples)


def level_points(points: np.ndarray, spec: PyramidSpec, rng: np.random.Generator | None = None) -> list[np.ndarray]:
    """Points of every level: (N_l, 3) float32. Level 0 is capped at ``spec.max_points``."""
    p0 = grid_subsample(points, spec.cell(0))
    if spec.max_points and len(p0) > spec.max_points:
        rng = rng if rng is not None else np.random.default_rng(0)
        keep = np.sort(rng.choice(len(p0), spec.max_points, replace=False))
        p0 = p0[keep]
    levels = [p0]
    for layer in range(1, spec.num_layers):
        levels.append(grid_subsample(levels[-1], spec.cell(layer)))
    return levels


def build_pyramid(points: np.ndarray, spec: PyramidSpec, rng: np.random.Generator | None = None,
                  workers: int = 1) -> FragmentPyramid:
    """The pyramid of one cloud: points (N, 3) at any density -> :class:`FragmentPyramid`."""
    pts = level_points(points, spec, rng)
    neighbors, pools, ups = [], [], []
    i32 = lambda a: a.astype(np.int32)  # noqa: E731  (halves the cache; widened when stacked)
    # one k-d tree per level, searched by its own points, the next level's (pooling) and the previous
    # level's (upsampling): the same searches as one tree per search
    trees = [support_tree(p) for p in pts]
    for layer, p in enumerate(pts):
        r = spec.radius(layer)
        neighbors.append(i32(radius_neighbors(p, p, r, spec.limit(layer), workers, trees[layer])))
        if layer + 1 < len(pts):
            pools.append(i32(radius_neighbors(pts[layer + 1], p, r, spec.limit(layer), workers, trees[layer])))
            ups.append(i32(nearest_neighbor(p, pts[layer + 1], workers, trees[layer + 1])))
    return FragmentPyramid(pts, neighbors, pools, ups)


def calibrate_limits(clouds: Iterable[np.ndarray], spec: PyramidSpec, keep_ratio: float = 0.8,
                     min_samples: int = 2000) -> tuple[int, ...]:
    """Per-level neighbour limits: the ``keep_ratio`` quantile of the neighbourhood sizes (as Predator).

    Reads clouds until every level has ``min_samples`` neighbourhoods (or the clouds run out).
    """
    counts: list[list[np.ndarray]] = [[] for _ in range(spec.num_layers)]
    for cloud in clouds:
        for layer, p in enumerate(level_points(cloud, spec)):
            counts[layer].append(neighbor_counts(p, p, spec.radius(layer)))
        if min(sum(len(c) for c in cs) for cs in counts) >= min_samples:
            break
    limits = []
    for cs in counts:
        allc = np.concatenate(cs) if cs else np.zeros(0, np.int64)
        limits.append(int(np.ceil(np.quantile(allc, keep_ratio))) if len(allc) else 1)
    return tuple(max(1, v) for v in limits)


# --------------------------------------------------------------------------- stacking


@dataclass
class TensorPyramid:
    """Torch pyramid of a stacked pair (source first); ``lengths`` (L, 2) = source/target counts (CPU)."""

    points: list[torch.Tensor]
    neighbors: list[torch.Tensor]
    pools: list[torch.Tensor]
    upsamples: list[torch.Tensor]
    lengths: torch.Tensor
    # per-batch scratch space (KPConv influences shared by the convolutions of a level)
    cache: dict = field(default_factory=dict, repr=False, compare=False)

    def to(self, device: torch.device | str) -> "TensorPyramid":
        mv = lambda xs: [x.to(device, non_blocking=True) for x in xs]  # noqa: E731
        # lengths stay on the CPU: they are read as Python ints (no device sync)
        return TensorPyramid(mv(self.points), mv(self.neighbors), mv(self.pools), mv(self.upsamples), self.lengths)

    def split(self, layer: int) -> tuple[int, int]:
        """Number of source and target points at ``layer`` (Python ints)."""
        a, b = self.lengths[layer].tolist()
        return int(a), int(b)


def _remap(idx: np.ndarray, n_own: int, offset: int, n_total: int) -> np.ndarray:
    idx = idx.astype(np.int64)
    return np.where(idx < n_own, idx + offset, n_total)


def _pad(a: np.ndarray, width: int, value: int) -> np.ndarray:
    if a.shape[1] == width:
        return a
    out = np.full((a.shape[0], width), value, dtype=a.dtype)
    out[:, : a.shape[1]] = a
    return out


def _stack_index(a: np.ndarray, b: np.ndarray, na_sup: int, nb_sup: int) -> np.ndarray:
    total = na_sup + nb_sup
    a2, b2 = _remap(a, na_sup, 0, total), _remap(b, nb_sup, na_sup, total)
    width = max(a2.shape[1], b2.shape[1])
    return np.concatenate([_pad(a2, width, total), _pad(b2, width, total)], 0)


def stack_pair(src: FragmentPyramid, tgt: FragmentPyramid) -> TensorPyramid:
    """Stack two fragment pyramids (source first) into one :class:`TensorPyramid` with global indices."""
    if src.num_layers != tgt.num_layers:
        raise ValueError(f"pyramids have {src.num_layers} and {tgt.num_layers} levels")
    L = src.num_layers
    ns = [len(p) for p in src.points]
    nt = [len(p) for p in tgt.points]
    points = [torch.from_numpy(np.concatenate([a, b], 0)) for a, b in zip(src.points, tgt.points)]
    neighbors = [torch.from_numpy(_stack_index(src.neighbors[l], tgt.neighbors[l], ns[l], nt[l])) for l in range(L)]
    pools = [torch.from_numpy(_stack_index(src.pools[l], tgt.pools[l], ns[l], nt[l])) for l in range(L - 1)]
    ups = [torch.from_numpy(_stack_index(src.upsamples[l], tgt.upsamples[l], ns[l + 1], nt[l + 1]))
           for l in range(L - 1)]
    lengths = torch.tensor([[a, b] for a, b in zip(ns, nt)], dtype=torch.long)
    return TensorPyramid(points, neighbors, pools, ups, lengths)


# --------------------------------------------------------------------------- cache


class PyramidCache:
    """LRU cache of fragment pyramids in memory, optionally mirrored to ``directory`` as ``.npz``.

    Keys are any hashable (e.g. ``(root, scene, fragment, spec.key())``); pyramids are stored in
    the fragment's own frame. A key names a fragment, not its content: a data set made again at the
    same root gives other points under the same key. :meth:`get`'s ``source`` (the
    :func:`points_fingerprint` of the points the pyramid is built from) is stored beside a file's
    pyramid and checked when the file is read, so a file made from other points is built again and
    overwritten instead of being used (the memory cache lives as long as one process's data).
    """

    def __init__(self, maxsize: int = 512, directory: str | Path | None = None):
        self.maxsize = maxsize
        self.directory = Path(directory) if directory else None
        self._mem: OrderedDict[Hashable, FragmentPyramid] = OrderedDict()
        self.hits = self.misses = 0
        self._warned = False

    def _path(self, key: Hashable) -> Path:
        assert self.directory is not None
        h = hashlib.sha1(repr(key).encode()).hexdigest()[:20]
        return self.directory / f"pyr_{h}.npz"

    def get(self, key: Hashable, build: Callable[[], FragmentPyramid],
            source: Callable[[], str] | None = None) -> FragmentPyramid:
        """The pyramid under ``key``: from memory, else from its file (when the file's stored source equals
        ``source()``, or both have none), else ``build()`` (then written to the file)."""
        if key in self._mem:
            self._mem.move_to_end(key)
            self.hits += 1
            return self._mem[key]
        src = source() if (source is not None and self.directory) else ""
        pyr = self._load(key, src) if self.directory else None
        if pyr is None:
            self.misses += 1
            pyr = build()
            if self.directory:
                self._save(key, pyr, src)
        else:
            self.hits += 1
        if self.maxsize > 0:
            self._mem[key] = pyr
            while len(self._mem) > self.maxsize:
                self._mem.popitem(last=False)
        return pyr

    def _save(self, key: Hashable, pyr: FragmentPyramid, source: str = "") -> None:
        """Writes the file whole, then renames it into place. A cache that cannot be written (a full disk) is
        not an error: the run goes on building its pyramids, with one warning."""
        path = self._path(key)
        arrays = {}
        for name in ("points", "neighbors", "pools", "upsamples"):
            for i, a in enumerate(getattr(pyr, name)):
                arrays[f"{name}_{i}"] = a
        tmp = path.with_suffix(f".tmp-{os.getpid()}-{secrets.token_hex(4)}.npz")  # no global random state drawn
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(tmp, key=np.array(repr(key)), source=np.array(source), **arrays)
            tmp.replace(path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            if not self._warned:
                self._warned = True
                warnings.warn(f"pyramid cache {self.directory}: not written ({exc}); pyramids are built instead",
                              stacklevel=2)

    def _load(self, key: Hashable, source: str = "") -> FragmentPyramid | None:
        path = self._path(key)
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:  # a cache file never runs code: a bad one is rebuilt
                if str(z["key"]) != repr(key):
                    return None
                stored = str(z["source"]) if "source" in z.files else ""
                if stored != source:  # made from other points
                    return None
                get = lambda name: [z[k] for k in sorted((k for k in z.files if k.startswith(name + "_")),  # noqa: E731
                                                         key=lambda s: int(s.rsplit("_", 1)[1]))]
                return FragmentPyramid(get("points"), get("neighbors"), get("pools"), get("upsamples"))
        except (OSError, ValueError, KeyError):
            return None


def points_fingerprint(points: np.ndarray) -> str:
    """A digest of a cloud's coordinates (N, 3): its shape, dtype and bytes (~1 ms for 100k points)."""
    a = np.ascontiguousarray(points)
    h = hashlib.blake2b(f"{a.shape}{a.dtype.str}".encode(), digest_size=16)
    h.update(a.data)
    return h.hexdigest()


def fragment_rng(key: Sequence[object]) -> np.random.Generator:
    """A generator seeded from a fragment key (deterministic point caps, so caching stays valid)."""
    seed = int.from_bytes(hashlib.sha1(repr(tuple(key)).encode()).digest()[:8], "little")
    return np.random.default_rng(seed)


__all__ = [
    "PyramidSpec", "FragmentPyramid", "TensorPyramid", "PyramidCache", "build_pyramid", "level_points",
    "calibrate_limits", "stack_pair", "fragment_rng",
]
