"""RGB-D frames of a data set in the 3DMatch layout, loaded for the 2D pretraining.

* :func:`list_sequences` ``(layout, scene) -> [(seq, frame_ids)]``: every ``frame-XXXXXX.color.png``
  under ``rgbd/<scene>/<seq>/`` (works for generated scenes and real frames alike; fragments are not
  needed).
* :func:`load_sequence` ``(layout, scene, seq, frame_ids, image_size) -> FrameSequence``: colors,
  depths, poses and intrinsics resized to the encoder's input size. Frames whose pose is unusable
  (NaN/inf, not rigid: real sequences have some) are skipped and counted; a missing or corrupt
  color/depth file is a :class:`pcrcg.errors.DataError` naming it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from pcrcg.data.layout import Layout, frame_paths, read_color, read_depth, read_intrinsics, read_pose
from pcrcg.errors import DataError
from pcrcg.vision.pretrain import resize_view


@dataclass
class FrameSequence:
    """Frames of one sequence of one scene at the pretraining resolution.

    colors (F, H, W, 3) uint8; depths (F, H, W) float32 metres; poses (F, 4, 4) camera-to-world;
    K (3, 3) scaled to (H, W); ``frame_ids`` (F,); ``skipped``: frames dropped for a bad pose.
    """

    scene: str
    seq: str
    frame_ids: list[int]
    colors: np.ndarray
    depths: np.ndarray
    poses: np.ndarray
    K: np.ndarray
    skipped: int = 0

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def name(self) -> str:
        return f"{self.scene}/{self.seq}"

    def subset(self, idx: Sequence[int]) -> "FrameSequence":
        idx = list(idx)
        return FrameSequence(self.scene, self.seq, [self.frame_ids[i] for i in idx], self.colors[idx],
                             self.depths[idx], self.poses[idx], self.K, self.skipped)


def list_sequences(layout: Layout, scene: str) -> list[tuple[str, list[int]]]:
    """``[(seq, sorted frame ids)]`` of a scene's RGB-D folder; DataError when it holds no frames."""
    d = layout.rgbd_dir(scene)
    if not d.is_dir():
        raise DataError(d, "RGB-D folder of the scene is missing (rgbd/<scene>/<seq>/frame-XXXXXX.*)")
    out = []
    for seq_dir in sorted(p for p in d.iterdir() if p.is_dir()):
        ids = sorted(int(p.name[6:12]) for p in seq_dir.glob("frame-*.color.png") if p.name[6:12].isdigit())
        if ids:
            out.append((seq_dir.name, ids))
    if not out:
        raise DataError(d, "no frame-XXXXXX.color.png files in any sequence folder")
    return out


def load_sequence(layout: Layout, scene: str, seq: str, frame_ids: Sequence[int],
                  image_size: Sequence[int] | None) -> FrameSequence:
    """Load and resize the frames ``frame_ids`` of ``scene/seq`` (see the module docstring)."""
    K0 = read_intrinsics(layout.intrinsics(scene))
    colors, depths, poses, ids = [], [], [], []
    K = K0
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
        color = read_color(cpath)
        depth = read_depth(dpath)
        if color.shape[:2] != depth.shape:
            raise DataError(dpath, f"depth is {depth.shape[1]}x{depth.shape[0]} but color is "
                                   f"{color.shape[1]}x{color.shape[0]}")
        c, d, K = resize_view(color, depth, K0, image_size)
        colors.append(c)
        depths.append(d)
        poses.append(pose)
        ids.append(int(fid))
    if not ids:
        raise DataError(layout.rgbd_dir(scene) / seq, "no frame with a usable pose")
    return FrameSequence(scene, seq, ids, np.stack(colors), np.stack(depths).astype(np.float32),
                         np.stack(poses), np.asarray(K, dtype=np.float64), skipped)
