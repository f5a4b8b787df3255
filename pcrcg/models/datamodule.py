"""Lightning data module over the 3DMatch layout: pairs with KPConv inputs precomputed in the collate.

The collate (:class:`PairCollate`) turns one :class:`~pcrcg.data.dataset.PairSample` into a
:class:`PairBatch`:

1. each fragment's pyramid (grid subsampling + radius neighbours, :mod:`pcrcg.models.kpconv.pyramid`)
   is built in the fragment's own frame, or taken from the per-fragment cache;
2. ground-truth correspondences (level-0 points closer than ``overlap_radius`` after the
   ground-truth motion) are found with a k-d tree;
3. in training, a rigid augmentation moves the pyramids (Predator's: a random rotation of one of the
   two fragments, chosen at random, plus small noise on the level-0 points; the same distribution as
   :func:`pcrcg.data.augment.augment_pair`, applied to the cached pyramid instead of the raw points);
   neighbour indices are rotation invariant and are reused as they are.

The lifting stage needs the level-0 points in the fragment's own frame (where its RGB-D views
are posed): they travel in the batch as ``src_frame_points`` / ``tgt_frame_points`` together with
the views, so the color features do not depend on the augmentation.

The training order is :class:`EpochSampler`'s: epoch ``e``'s permutation comes from ``(seed, e)``
and each pair's augmentation from ``(seed, e, rank, position)``, never from a global random state.
The train loader saves its position in checkpoints (Lightning's ``state_dict`` interface for
loaders), so a run resumed from a ``last.ckpt`` written mid-epoch sees the rest of that epoch in
the same order with the same augmentations, bit for bit the uninterrupted run (with
:class:`pcrcg.models.train.GlobalRngState` for the model's own draws).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from pcrcg.data.dataset import PairDataset, PairSample, View
from pcrcg.errors import ConfigError, DataError
from pcrcg.geometry import invert, make_transform, random_rotation, transform_points
from pcrcg.fields import NodeSettings
from pcrcg.models.kpconv.ops import radius_pairs
from pcrcg.models.kpconv.pyramid import (
    FragmentPyramid,
    PyramidCache,
    PyramidSpec,
    TensorPyramid,
    build_pyramid,
    calibrate_limits,
    fragment_rng,
    points_fingerprint,
    stack_pair,
)


@dataclass
class AugmentConfig(NodeSettings):
    """Rotate one fragment (chosen at random) about its origin by an angle uniform in
    [0, ``rotation_range_deg``] about a random axis; Gaussian noise of ``noise_std`` m on the
    level-0 points of both. Predator's noise is uniform of width 5 mm (std 1.4 mm), hence 0.0015."""

    enabled: bool = True
    rotation_range_deg: float = 360.0
    noise_std: float = 0.0015


@dataclass
class PairBatch:
    """One pair ready for the network (tensors) plus its views and identity.

    pyramid: stacked source-then-target KPConv inputs (augmented frames);
    transform (4, 4) float32: source -> target in the augmented frames;
    corr (C, 2) long: local (source, target) indices of level-0 correspondences;
    src_frame_points (Ns, 3) / tgt_frame_points (Nt, 3) float32 NumPy: level-0 points in each
    fragment's own frame (where its views are posed; they stay on the CPU, the lifting stage moves them);
    src_aug / tgt_aug (4, 4): the augmentation applied (own frame -> augmented frame);
    matches: 2D matches between the views for explicit projection (``{(a, b): Matches}``) or None.
    """

    pyramid: TensorPyramid
    transform: torch.Tensor
    corr: torch.Tensor
    src_frame_points: np.ndarray
    tgt_frame_points: np.ndarray
    src_aug: torch.Tensor
    tgt_aug: torch.Tensor
    src_views: list[View] = field(default_factory=list)
    tgt_views: list[View] = field(default_factory=list)
    scene: str = ""
    i: int = -1
    j: int = -1
    overlap: float = float("nan")
    matches: Any = None

    @property
    def n_src(self) -> int:
        return self.pyramid.split(0)[0]

    def to(self, device: torch.device | str) -> "PairBatch":
        mv = lambda t: t.to(device, non_blocking=True)  # noqa: E731
        return PairBatch(self.pyramid.to(device), mv(self.transform), mv(self.corr), self.src_frame_points,
                         self.tgt_frame_points, mv(self.src_aug), mv(self.tgt_aug), self.src_views,
                         self.tgt_views, self.scene, self.i, self.j, self.overlap, self.matches)


def augment_transforms(rng: np.random.Generator, cfg: AugmentConfig) -> tuple[np.ndarray, np.ndarray]:
    """(A_src, A_tgt) 4x4: one of them a random rotation, the other the identity (as Predator)."""
    R = random_rotation(rng, np.radians(cfg.rotation_range_deg))
    A = make_transform(R, np.zeros(3))
    if rng.random() < 0.5:
        return A, np.eye(4)
    return np.eye(4), A


def draw_seed(*key: int) -> int:
    """A 31-bit seed from integers (``numpy.random.SeedSequence``): the same key, the same seed."""
    return int(np.random.SeedSequence([int(k) for k in key]).generate_state(1)[0] >> 1)


class EpochSampler(DistributedSampler):
    """The training order: each epoch a permutation of the pairs drawn from ``seed + epoch``
    (``DistributedSampler``'s rule, sharded over ``num_replicas`` ranks, padded to equal length),
    each index yielded as ``(index, augmentation seed)`` with the seed from ``(seed, epoch, rank,
    position)``. No global random state is read or advanced.

    The epoch of an iteration is the running fit's (``position``: ``() -> (epoch, batches done in it,
    batches per epoch)``, read when the iteration starts), or without one a count of iterations.
    ``state_dict()`` is the fit's position, ``{"epoch", "done", "epoch_batches"}``; after
    ``load_state_dict`` an iteration of that epoch leaves out its first ``done`` items (none when
    ``done`` reached ``epoch_batches``: the fit resumes at the next epoch)."""

    def __init__(self, dataset: Sequence[Any], seed: int = 0, num_replicas: int = 1, rank: int = 0,
                 position: Callable[[], tuple[int, int, int]] | None = None):
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=True, seed=int(seed))
        self.position = position
        self._skip: tuple[int, int] | None = None  # (epoch, items its iterations leave out)
        self._count = 0  # iterations started, the epoch when there is no fit to ask

    def set_epoch(self, epoch: int) -> None:
        """Ignored: Lightning 2.6 passes one too many after resuming from a checkpoint of an epoch's end
        (``epoch_progress.current.processed``); the fit's ``current_epoch`` is right."""

    def __iter__(self):  # type: ignore[override]
        # the epoch is read here, when the iteration starts: a loader with workers starts one as soon as
        # its iterator exists, and Lightning may make an iterator it never uses (resuming at an epoch's end)
        self.epoch = int(self.position()[0]) if self.position is not None else self._count
        self._count = self.epoch + 1
        if self._skip is not None and self._skip[0] < self.epoch:
            self._skip = None
        skip = self._skip[1] if self._skip is not None and self._skip[0] == self.epoch else 0
        order = list(super().__iter__())
        for pos in range(skip, len(order)):
            yield order[pos], draw_seed(self.seed, self.epoch, self.rank, pos)

    def state_dict(self) -> dict[str, int]:
        epoch, done, per_epoch = self.position() if self.position is not None else (self.epoch, 0, len(self))
        per_epoch = per_epoch if per_epoch >= 0 else len(self)
        return {"epoch": int(epoch), "done": int(done), "epoch_batches": int(per_epoch)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        epoch, done = int(state["epoch"]), int(state["done"])
        if done >= int(state.get("epoch_batches", len(self))):
            epoch, done = epoch + 1, 0
        self._count = epoch
        self._skip = (epoch, done)


class _SeededPairs(Dataset):
    """``dataset[(index, seed)] -> (dataset[index], seed)``: the sample with its augmentation seed."""

    def __init__(self, pairs: Sequence[PairSample]):
        self.pairs = pairs

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, key: tuple[int, int]) -> tuple[PairSample, int]:
        index, seed = key
        return self.pairs[index], seed


class ResumableLoader(DataLoader):
    """A ``DataLoader`` whose :class:`EpochSampler` position goes into Lightning checkpoints and comes back."""

    def state_dict(self) -> dict[str, int]:
        return self.sampler.state_dict()

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.sampler.load_state_dict(state)


class PairCollate:
    """Callable collate: ``[PairSample] -> PairBatch`` (batch size 1, as Predator and the paper).
    A sample may come as ``(PairSample, seed)`` (:class:`EpochSampler`): its augmentation is drawn
    from ``seed``; a bare sample draws its seed from torch's global generator."""

    def __init__(self, spec: PyramidSpec, overlap_radius: float, augment: AugmentConfig | None = None,
                 cache: PyramidCache | None = None, root: str = "", workers: int = 1,
                 match_fn: Callable[[PairSample], Any] | None = None):
        self.spec = spec
        self.overlap_radius = float(overlap_radius)
        self.augment = augment if augment is not None and augment.enabled else None
        self.cache = cache if cache is not None else PyramidCache(maxsize=0)
        self.root = str(root)
        self.workers = workers
        self.match_fn = match_fn  # 2D matching for explicit projection, done here on the CPU (workers)

    def pyramid(self, scene: str, frag: int, points: np.ndarray) -> FragmentPyramid:
        """The fragment's pyramid, cached under (data root, scene, fragment, sizes). The draw that caps level 0
        at ``spec.max_points`` is seeded by (scene, fragment, sizes) alone: the same data set gives the same
        pyramids wherever its folder lies (the root's path once seeded it, so a copy or a checkout
        elsewhere trained on other points)."""
        rng = fragment_rng((scene, int(frag), self.spec.key()))
        if frag < 0 or not scene:  # anonymous cloud: no caching
            return build_pyramid(points, self.spec, rng, self.workers)
        return self.cache.get((self.root, scene, int(frag), self.spec.key()),
                              lambda: build_pyramid(points, self.spec, rng, self.workers),
                              lambda: points_fingerprint(points))

    def __call__(self, samples: Sequence[PairSample]) -> PairBatch:
        if len(samples) != 1:
            raise ConfigError("trainer.batch_size", len(samples), "1 (pairs are stacked, as in Predator)")
        s, seed = samples[0] if isinstance(samples[0], tuple) else (samples[0], None)
        src = self.pyramid(s.scene, s.j, s.src_points)
        tgt = self.pyramid(s.scene, s.i, s.tgt_points)
        T = np.asarray(s.transform, dtype=np.float64)
        corr = radius_pairs(transform_points(T, src.points[0].astype(np.float64)), tgt.points[0], self.overlap_radius)
        a_src, a_tgt = np.eye(4), np.eye(4)
        src_aug, tgt_aug = src, tgt
        if self.augment is not None:
            if seed is None:
                seed = int(torch.randint(0, 2**31 - 1, (1,)).item())
            rng = np.random.default_rng(seed)
            a_src, a_tgt = augment_transforms(rng, self.augment)
            src_aug, tgt_aug = src.transformed(a_src), tgt.transformed(a_tgt)
            T = a_tgt @ T @ invert(a_src)
            if self.augment.noise_std > 0:
                for pyr in (src_aug, tgt_aug):
                    p0 = pyr.points[0]
                    pyr.points[0] = (p0 + rng.normal(0.0, self.augment.noise_std, p0.shape)).astype(np.float32)
        return PairBatch(
            pyramid=stack_pair(src_aug, tgt_aug),
            transform=torch.from_numpy(T.astype(np.float32)),
            corr=torch.from_numpy(corr),
            src_frame_points=src.points[0],
            tgt_frame_points=tgt.points[0],
            src_aug=torch.from_numpy(a_src.astype(np.float32)),
            tgt_aug=torch.from_numpy(a_tgt.astype(np.float32)),
            src_views=list(s.src_views),
            tgt_views=list(s.tgt_views),
            scene=s.scene, i=int(s.i), j=int(s.j), overlap=float(s.overlap),
            matches=self.match_fn(s) if self.match_fn is not None else None,
        )


def pair_from_clouds(src_points: np.ndarray, tgt_points: np.ndarray, transform: np.ndarray | None = None,
                     src_views: Sequence[View] = (), tgt_views: Sequence[View] = ()) -> PairSample:
    """A :class:`PairSample` from two user clouds (transform = identity when unknown)."""
    z = lambda p: np.zeros_like(np.asarray(p, np.float32))  # noqa: E731
    return PairSample(scene="", i=-1, j=-1, src_points=np.asarray(src_points, np.float32),
                      tgt_points=np.asarray(tgt_points, np.float32), src_colors=z(src_points),
                      tgt_colors=z(tgt_points), transform=np.eye(4) if transform is None else np.asarray(transform),
                      overlap=float("nan"), src_views=list(src_views), tgt_views=list(tgt_views))


class PairDataModule(L.LightningDataModule):
    """Train/val pairs of a data set in the 3DMatch layout (or any sequences of :class:`PairSample`).

    ``neighbor_limits`` (one per level) is calibrated on the training fragments at ``setup`` when
    not given (the ``keep_ratio`` quantile of the neighbourhood sizes, as Predator) and saved in
    checkpoints (``state_dict``), so a resumed run and inference use the same limits.
    """

    def __init__(self, root: str | Path | None = None, n_views: int = 0, voxel_size: float = 0.025,
                 num_layers: int = 4, conv_radius: float = 2.5, max_points: int = 30000,
                 overlap_radius: float = 1.5, neighbor_limits: Sequence[int] | None = None,
                 keep_ratio: float = 0.8, calibration_fragments: int = 20, augment: Mapping[str, Any] | None = None,
                 num_workers: int = 0, batch_size: int = 1, cache_dir: str | Path | None = None,
                 cache_size: int = 1024, datasets: Mapping[str, Sequence[PairSample]] | None = None,
                 train_split: str = "train", val_split: str = "val",
                 match_fn: Callable[[PairSample], Any] | None = None, seed: int = 0):
        super().__init__()
        if batch_size != 1:
            raise ConfigError("trainer.batch_size", batch_size, "1 (pairs are stacked, as in Predator)")
        if root is None and not datasets:
            raise ConfigError("data.root", root, "a data set folder in the 3DMatch layout")
        self.root = str(root) if root is not None else ""
        self.n_views = int(n_views)
        self.voxel_size, self.num_layers, self.conv_radius = float(voxel_size), int(num_layers), float(conv_radius)
        self.max_points = int(max_points)
        self.overlap_radius = float(overlap_radius) * self.voxel_size  # metres
        self.limits: tuple[int, ...] | None = tuple(int(v) for v in neighbor_limits) if neighbor_limits else None
        self.keep_ratio, self.calibration_fragments = float(keep_ratio), int(calibration_fragments)
        self.augment = AugmentConfig.from_mapping(augment)
        self.num_workers = int(num_workers)
        self.cache = PyramidCache(cache_size, cache_dir)
        self._given = dict(datasets or {})
        self.train_split, self.val_split = train_split, val_split
        self.sets: dict[str, Sequence[PairSample]] = {}
        self.match_fn = match_fn
        self.seed = int(seed)  # the training order and augmentations (EpochSampler)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        return {"neighbor_limits": list(self.limits) if self.limits else None}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("neighbor_limits"):
            self.limits = tuple(int(v) for v in state["neighbor_limits"])

    def spec(self) -> PyramidSpec:
        if self.limits is None:
            raise RuntimeError("neighbour limits are not calibrated yet: call setup() first")
        return PyramidSpec(self.voxel_size, self.num_layers, self.conv_radius, self.limits, self.max_points)

    # ------------------------------------------------------------------ data
    def dataset(self, split: str) -> Sequence[PairSample]:
        if split not in self.sets:
            if split in self._given:
                self.sets[split] = self._given[split]
            else:
                self.sets[split] = PairDataset(self.root, split, self.n_views)
        return self.sets[split]

    def _calibration_clouds(self, ds: Sequence[PairSample]):
        seen = set()
        if isinstance(ds, PairDataset):
            for p in ds.pairs:
                for frag in (p.i, p.j):
                    if (p.scene, frag) in seen:
                        continue
                    seen.add((p.scene, frag))
                    yield ds.fragment(p.scene, frag)[0]
                    if len(seen) >= self.calibration_fragments:
                        return
        else:
            for k in range(min(len(ds), self.calibration_fragments)):
                yield ds[k].src_points
                yield ds[k].tgt_points

    def calibrate(self) -> tuple[int, ...]:
        spec = PyramidSpec(self.voxel_size, self.num_layers, self.conv_radius, (), self.max_points)
        self.limits = calibrate_limits(self._calibration_clouds(self.dataset(self.train_split)), spec, self.keep_ratio)
        return self.limits

    def setup(self, stage: str | None = None) -> None:
        if stage == "fit" and self.train_split not in self._given:
            ds = self.dataset(self.train_split)
            if len(ds) == 0:
                where = ds.layout.pairs_file(self.train_split) if isinstance(ds, PairDataset) else self.root
                raise DataError(where, "no training pairs: a test-only data set (data=threedmatch's real scene) trains "
                                "nothing; train on generated data and evaluate the checkpoint here (python -m "
                                "pcrcg.evaluate mode=benchmark method=learned checkpoint=FILE data.root=...)")
        if self.limits is None:
            self.calibrate()

    def collate(self, train: bool) -> PairCollate:
        return PairCollate(self.spec(), self.overlap_radius, self.augment if train else None, self.cache, self.root,
                           match_fn=self.match_fn)

    def _make_loader(self, cls: type[DataLoader], dataset: Any, train: bool, **kw: Any) -> DataLoader:
        # an own generator: making an iterator draws the workers' base seed, not from torch's global one
        return cls(dataset, batch_size=1, num_workers=self.num_workers, collate_fn=self.collate(train),
                   persistent_workers=self.num_workers > 0, generator=torch.Generator().manual_seed(self.seed), **kw)

    def _loader(self, split: str) -> DataLoader:
        """The pairs of a split in order, without augmentation."""
        return self._make_loader(DataLoader, self.dataset(split), False, shuffle=False)

    def _train_position(self) -> tuple[int, int, int]:
        """(epoch, batches whose training step ran in it, batches per epoch or -1 before it is known) of the
        running fit."""
        t = self.trainer
        per_epoch = t.num_training_batches  # inf until the fit has sized its loader
        return (int(t.current_epoch), int(t.fit_loop.epoch_loop.batch_progress.current.processed),
                int(per_epoch) if per_epoch != float("inf") else -1)

    def train_dataloader(self) -> DataLoader:
        """The training pairs in :class:`EpochSampler` order (sharded by rank under DDP), resumable."""
        t = self.trainer
        world, rank = (int(t.world_size), int(t.global_rank)) if t is not None else (1, 0)
        pairs = self.dataset(self.train_split)
        sampler = EpochSampler(pairs, self.seed, world, rank, self._train_position if t is not None else None)
        return self._make_loader(ResumableLoader, _SeededPairs(pairs), True, sampler=sampler)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_split)

    def benchmark_dataloader(self, benchmark: str) -> DataLoader:
        """Pairs of a test benchmark (``3DMatch`` / ``3DLoMatch``) in order, no augmentation."""
        return self._loader(benchmark)

    @classmethod
    def from_config(cls, data_root: str | Path | None, model_cfg: Mapping[str, Any], trainer_cfg: Mapping[str, Any],
                    n_views: int = 0, **kw: Any) -> "PairDataModule":
        """Built from ``conf/model/predator.yaml`` and ``conf/trainer/*.yaml`` sections."""
        loss = dict(model_cfg.get("loss", {}) or {})
        return cls(
            root=data_root, n_views=n_views, voxel_size=model_cfg["voxel_size"], num_layers=model_cfg["num_layers"],
            conv_radius=model_cfg.get("conv_radius", 2.5), max_points=model_cfg.get("max_points", 30000),
            overlap_radius=loss.get("overlap_radius", 1.5), neighbor_limits=model_cfg.get("neighbor_limits"),
            keep_ratio=model_cfg.get("neighbor_keep_ratio", 0.8), augment=trainer_cfg.get("augment"),
            num_workers=trainer_cfg.get("num_workers", 0), batch_size=trainer_cfg.get("batch_size", 1),
            cache_dir=trainer_cfg.get("cache_dir"), cache_size=int(trainer_cfg.get("cache_size") or 1024), **kw)
