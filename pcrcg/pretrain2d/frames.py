"""RGB-D frames of a data set in the 3DMatch layout, indexed for the 2D pretraining.

* :func:`list_sequences` ``(layout, scene) -> [(seq, frame_ids)]``: every ``frame-XXXXXX.color.png|.jpg``
  under ``rgbd/<scene>/<seq>/`` (generated scenes and real frames alike; fragments are not needed).
* :func:`load_sequence` ``(layout, scene, seq, frame_ids, image_size, coarse_stride, cache) ->
  FrameSequence``: reads every frame once to keep its pose and a coarse depth map (for the pair
  selection); the frames at the encoder's input size are kept in a shared LRU :class:`FrameCache`
  and re-read from disk when evicted (a paper-scale data set does not fit in memory).
  Frames whose pose is unusable (NaN/inf, not rigid: real sequences have some) are skipped and
  counted; a missing or corrupt color/depth file is a :class:`pcrcg.errors.DataError` naming it.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from pcrcg.data.layout import Layout, frame_paths, read_color, read_depth, read_intrinsics, read_pose
from pcrcg.data.layout import frame_ids as frames_in
from pcrcg.errors import DataError
from pcrcg.vision.pretrain import resize_depth, resize_view


class FrameCache:
    """LRU cache of resized frames ``(color (H, W, 3) uint8, depth (H, W) float32)`` keyed by color path."""

    def __init__(self, capacity: int):
        self.capacity = max(0, int(capacity))
        self._items: OrderedDict[str, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.misses = 0

    def __len__(self) -> int:
        return len(self._items)

    def full(self) -> bool:
        return len(self._items) >= self.capacity

    def get(self, key: str) -> tuple[np.ndarray, np.ndarray] | None:
        item = self._items.get(key)
        if item is not None:
            self._items.move_to_end(key)
        return item

    def put(self, key: str, item: tuple[np.ndarray, np.ndarray]) -> None:
        if self.capacity == 0:
            return
        self._items[key] = item
        self._items.move_to_end(key)
        while len(self._items) > self.capacity:
            self._items.popitem(last=False)


def _read_frame(cpath, dpath, K0: np.ndarray, image_size: Sequence[int] | None, with_color: bool = True):
    depth = read_depth(dpath)
    color = read_color(cpath) if with_color else None
    if color is not None and color.shape[:2] != depth.shape:
        raise DataError(dpath, f"depth is {depth.shape[1]}x{depth.shape[0]} but color is "
                               f"{color.shape[1]}x{color.shape[0]}")
    if color is None:
        color = np.zeros(depth.shape + (3,), np.uint8)
    return resize_view(color, depth, K0, image_size)


@dataclass
class FrameSequence:
    """Frames of one sequence of one scene.

    ``poses`` (F, 4, 4) camera-to-world; ``K`` (3, 3) at the encoder's input size; ``coarse_depths``
    (F, h, w) float32 and ``coarse_K`` for the pair selection; :meth:`frame` gives
    ``(color (H, W, 3) uint8, depth (H, W) float32)`` at the input size. ``skipped``: frames dropped
    for a bad pose.
    """

    scene: str
    seq: str
    frame_ids: list[int]
    poses: np.ndarray
    K: np.ndarray
    coarse_depths: np.ndarray
    coarse_K: np.ndarray
    layout: Layout
    image_size: tuple[int, int] | None
    K_native: np.ndarray
    cache: FrameCache = field(repr=False, default_factory=lambda: FrameCache(0))
    skipped: int = 0

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def name(self) -> str:
        return f"{self.scene}/{self.seq}"

    def paths(self, i: int):
        return frame_paths(self.layout.frame_prefix(self.scene, self.seq, self.frame_ids[i]))

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(color, depth) of frame ``i`` at the input size (cached)."""
        cpath, dpath, _ = self.paths(i)
        key = str(cpath)
        item = self.cache.get(key)
        if item is None:
            self.cache.misses += 1
            c, d, _ = _read_frame(cpath, dpath, self.K_native, self.image_size)
            item = (c, d)
            self.cache.put(key, item)
        return item

    def subset(self, idx: Sequence[int]) -> "FrameSequence":
        idx = list(idx)
        return FrameSequence(self.scene, self.seq, [self.frame_ids[i] for i in idx], self.poses[idx], self.K,
                             self.coarse_depths[idx], self.coarse_K, self.layout, self.image_size, self.K_native,
                             self.cache, self.skipped)


def list_sequences(layout: Layout, scene: str) -> list[tuple[str, list[int]]]:
    """``[(seq, sorted frame ids)]`` of a scene's RGB-D folder; DataError when it holds no frames."""
    d = layout.rgbd_dir(scene)
    if not d.is_dir():
        raise DataError(d, "RGB-D folder of the scene is missing (rgbd/<scene>/<seq>/frame-XXXXXX.*)")
    out = []
    for seq_dir in sorted(p for p in d.iterdir() if p.is_dir()):
        ids = frames_in(seq_dir)
        if ids:
            out.append((seq_dir.name, ids))
    if not out:
        raise DataError(d, "no frame-XXXXXX.color.png or .color.jpg files in any sequence folder")
    return out


def coarse_size(image_size: Sequence[int], stride: int) -> tuple[int, int]:
    return max(1, int(image_size[0]) // stride), max(1, int(image_size[1]) // stride)


def load_sequence(layout: Layout, scene: str, seq: str, frame_ids: Sequence[int], image_size: Sequence[int] | None,
                  coarse_stride: int = 8, cache: FrameCache | None = None) -> FrameSequence:
    """Index the frames ``frame_ids`` of ``scene/seq`` (see the module docstring)."""
    cache = cache if cache is not None else FrameCache(0)
    K0 = read_intrinsics(layout.intrinsics(scene))
    size = tuple(int(s) for s in image_size) if image_size is not None else None
    poses, ids, coarse = [], [], []
    K = cK = None
    skipped = 0
    for fid in frame_ids:
        cpath, dpath, ppath = frame_paths(layout.frame_prefix(scene, seq, fid))
        try:
            pose = read_pose(ppath)
        except DataError:
            if not ppath.is_file():
                raise
            skipped += 1
            continue
        keep = not cache.full()
        c, d, Kf = _read_frame(cpath, dpath, K0, size, with_color=keep)
        if keep:
            cache.put(str(cpath), (c, d))
        K = Kf
        dc, cK = resize_depth(d, Kf, coarse_size(d.shape, coarse_stride))
        coarse.append(dc)
        poses.append(pose)
        ids.append(int(fid))
    if not ids:
        raise DataError(layout.rgbd_dir(scene) / seq, "no frame with a usable pose")
    return FrameSequence(scene, seq, ids, np.stack(poses), np.asarray(K, dtype=np.float64),
                         np.stack(coarse).astype(np.float32), np.asarray(cK, dtype=np.float64), layout,
                         size, K0, cache, skipped)
