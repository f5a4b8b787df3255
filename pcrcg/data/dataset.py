"""PyTorch dataset over the 3DMatch layout: pairs of fragments with their RGB-D views.

A sample (``PairDataset[k]``) is a :class:`PairSample`:

* ``src_points`` (N, 3) float32 and ``tgt_points`` (M, 3) float32, each in its own fragment frame;
  ``src`` is fragment ``j`` and ``tgt`` fragment ``i`` of the ``gt.log`` entry ``i j``;
* ``src_colors`` / ``tgt_colors`` (N, 3) / (M, 3) float32 in [0, 1] (zeros when the file has none);
* ``transform`` (4, 4) float64 mapping ``src`` into ``tgt``;
* ``src_views`` / ``tgt_views``: lists of :class:`View` in the order first, last, middle frame
  of the fragment (``views=k`` keeps the first k); empty when ``n_views == 0`` or the data has no
  ``.info.txt``/frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from pcrcg.data.layout import (
    BENCHMARKS,
    FragmentInfo,
    Layout,
    PairRecord,
    color_camera,
    color_to_depth_camera,
    frame_paths,
    read_color,
    read_cloud,
    read_depth,
    read_fragment_info,
    read_gt_log,
    read_gt_overlap,
    read_intrinsics,
    read_pairs,
    read_pose,
)
from pcrcg.errors import DataError
from pcrcg.geometry import invert


@dataclass
class View:
    """One RGB-D frame of a fragment.

    color (H, W, 3) uint8 RGB; depth (H, W) float32 metres (0 = none); intrinsics (3, 3);
    pose (4, 4) camera-to-*fragment* (the fragment frame is the camera of its first frame).
    ``color_path`` identifies the image (cache key for 2D matches).
    """

    color: np.ndarray
    depth: np.ndarray
    intrinsics: np.ndarray
    pose: np.ndarray
    frame_id: int
    color_path: str

    def transformed(self, T: np.ndarray) -> "View":
        """The same view after the fragment is moved by the rigid ``T`` (4x4)."""
        return View(self.color, self.depth, self.intrinsics, T @ self.pose, self.frame_id, self.color_path)


@dataclass
class PairSample:
    scene: str
    i: int
    j: int
    src_points: np.ndarray
    tgt_points: np.ndarray
    src_colors: np.ndarray
    tgt_colors: np.ndarray
    transform: np.ndarray
    overlap: float
    src_views: list[View] = field(default_factory=list)
    tgt_views: list[View] = field(default_factory=list)


def view_frame_ids(info: FragmentInfo, n_views: int) -> list[int]:
    """Frame ids of the first ``n_views`` of (first, last, middle) of a fragment."""
    if not 0 <= n_views <= 3:
        raise ValueError(f"n_views must be 0..3, got {n_views}")
    first, last = info.first_frame, info.last_frame
    ids = [first, last, (first + last) // 2]
    return ids[:n_views]


def load_views(layout: Layout, scene: str, frag: int, n_views: int) -> list[View]:
    """The RGB-D views of fragment ``frag`` of ``scene``; poses relative to the fragment frame."""
    if n_views == 0:
        return []
    info = read_fragment_info(layout.fragment_info(scene, frag))
    K = read_intrinsics(layout.intrinsics(scene))
    K_color = color_camera(layout, scene, K)
    first_pose = read_pose(frame_paths(layout.frame_prefix(scene, info.seq, info.first_frame))[2])
    world_to_frag = invert(first_pose)
    views = []
    for fid in view_frame_ids(info, n_views):
        cpath, dpath, ppath = frame_paths(layout.frame_prefix(scene, info.seq, fid))
        color = read_color(cpath)
        depth = read_depth(dpath)
        if color.shape[:2] != depth.shape:
            raise DataError(dpath, f"depth is {depth.shape[1]}x{depth.shape[0]} but color is "
                                   f"{color.shape[1]}x{color.shape[0]}")
        if K_color is not None:
            color = color_to_depth_camera(color, K_color, K)
        pose = world_to_frag @ read_pose(ppath)
        views.append(View(color, depth, K.copy(), pose, fid, str(cpath)))
    return views


def benchmark_pairs(layout: Layout, benchmark: str, scenes: Sequence[str] | None = None) -> list[PairRecord]:
    """All pairs of a test benchmark (gt.log), with overlaps from gt_overlap.log when present."""
    if benchmark not in BENCHMARKS:
        raise ValueError(f"benchmark must be one of {BENCHMARKS}, got {benchmark!r}")
    scenes = list(scenes) if scenes is not None else sorted(
        p.name for p in layout.benchmark_dir(benchmark).iterdir() if p.is_dir()
    )
    out = []
    for scene in scenes:
        d = layout.benchmark_dir(benchmark, scene)
        recs = read_gt_log(d / "gt.log", scene)
        ov = read_gt_overlap(d / "gt_overlap.log") if (d / "gt_overlap.log").is_file() else {}
        for r in recs:
            out.append(PairRecord(scene, r.i, r.j, r.transform, ov.get((r.i, r.j), float("nan")), r.n_fragments))
    return out


class PairDataset:
    """Map-style dataset of fragment pairs (usable as a ``torch.utils.data.Dataset``).

    ``split`` is ``train``/``val`` (pairs files) or a benchmark name (``3DMatch``/``3DLoMatch``).
    Fragments are cached in memory after the first read (they are small and re-read every epoch).
    """

    def __init__(self, root: str | Path, split: str, n_views: int = 0, cache: bool = True):
        self.layout = Layout(root)
        if not self.layout.root.is_dir():
            raise DataError(self.layout.root, "data root does not exist (run `python -m pcrcg.prepare`)")
        self.split = split
        self.n_views = n_views
        if split in BENCHMARKS:
            self.pairs = benchmark_pairs(self.layout, split)
        else:
            self.pairs = read_pairs(self.layout.pairs_file(split))
        self._cache: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] | None = {} if cache else None

    def __len__(self) -> int:
        return len(self.pairs)

    def fragment(self, scene: str, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Points (N, 3) float32 and colors (N, 3) float32 of one fragment."""
        key = (scene, i)
        if self._cache is not None and key in self._cache:
            return self._cache[key]
        pts, cols = read_cloud(self.layout.fragment(scene, i))
        if cols is None:
            cols = np.zeros_like(pts)
        if self._cache is not None:
            self._cache[key] = (pts, cols)
        return pts, cols

    def __getitem__(self, k: int) -> PairSample:
        p = self.pairs[k]
        tgt_pts, tgt_cols = self.fragment(p.scene, p.i)
        src_pts, src_cols = self.fragment(p.scene, p.j)
        return PairSample(
            scene=p.scene,
            i=p.i,
            j=p.j,
            src_points=src_pts,
            tgt_points=tgt_pts,
            src_colors=src_cols,
            tgt_colors=tgt_cols,
            transform=p.transform.copy(),
            overlap=p.overlap,
            src_views=load_views(self.layout, p.scene, p.j, self.n_views),
            tgt_views=load_views(self.layout, p.scene, p.i, self.n_views),
        )
