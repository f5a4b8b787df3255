"""From an RGB-D sequence in the layout to fragments, pairs and benchmark files.

Generated and real frames go through exactly this code: frames are read back from
``<root>/rgbd/<scene>/<seq>/`` (checked first), fused in chunks of ``frames_per_fragment`` into
``cloud_bin_<i>.ply`` (+ ``.info.txt``), then every pair of fragments gets its overlap, and the
pairs with overlap >= 10% become training/validation pairs or test benchmark entries.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from pcrcg.data.fusion import FusionConfig, fuse_frames
from pcrcg.data.layout import (
    BENCHMARKS,
    FragmentInfo,
    Layout,
    PairRecord,
    frame_paths,
    color_camera,
    color_to_depth_camera,
    read_color,
    read_depth,
    read_intrinsics,
    read_pose,
    write_fragment_info,
    write_gt_info,
    write_gt_log,
    write_gt_overlap,
    write_ply,
)
from pcrcg.data.pairs import PairConfig, benchmark_of, info_matrix, overlap_ratio, voxel_downsample
from pcrcg.errors import DataError
from pcrcg.geometry import invert


@dataclass
class SceneResult:
    scene: str
    n_fragments: int
    points_per_fragment: list[int]
    pairs: list[PairRecord] = field(default_factory=list)  # overlap >= min_overlap, i < j
    all_overlaps: list[float] = field(default_factory=list)  # every pair i < j, for histograms
    benchmark_counts: dict[str, int] = field(default_factory=dict)


def check_frames(layout: Layout, scene: str, seq: str, frame_ids: Sequence[int]) -> np.ndarray:
    """Check every frame of a sequence before any long work; returns the intrinsics (3, 3).

    Missing files, undecodable or truncated PNGs, depth/color size mismatch, non-rigid or NaN
    poses raise :class:`DataError` naming the file.
    """
    K = read_intrinsics(layout.intrinsics(scene))
    size = None
    for fid in frame_ids:
        cpath, dpath, ppath = frame_paths(layout.frame_prefix(scene, seq, fid))
        color = read_color(cpath)
        depth = read_depth(dpath)
        if color.shape[:2] != depth.shape:
            raise DataError(dpath, f"depth is {depth.shape[1]}x{depth.shape[0]} but color is "
                                   f"{color.shape[1]}x{color.shape[0]}")
        if size is None:
            size = depth.shape
        elif depth.shape != size:
            raise DataError(dpath, f"frame size {depth.shape} differs from the sequence's {size}")
        read_pose(ppath)
    return K


def fragment_chunks(frame_ids: Sequence[int], frames_per_fragment: int) -> list[list[int]]:
    """Consecutive chunks of ``frames_per_fragment`` frames; a last chunk shorter than half is dropped."""
    ids = list(frame_ids)
    chunks = [ids[k : k + frames_per_fragment] for k in range(0, len(ids), frames_per_fragment)]
    if len(chunks) > 1 and len(chunks[-1]) < max(1, frames_per_fragment // 2):
        chunks.pop()
    return chunks


def fuse_sequence(
    layout: Layout, scene: str, seq: str, frame_ids: Sequence[int], frames_per_fragment: int,
    fusion: FusionConfig, first_index: int = 0,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Fuse a sequence into fragments written to ``<root>/fragments/<scene>/``.

    Returns each fragment's points (fragment frame) and its first frame's camera-to-world pose.
    """
    K = read_intrinsics(layout.intrinsics(scene))
    K_color = color_camera(layout, scene, K)
    out_dir = layout.fragments_dir(scene)
    out_dir.mkdir(parents=True, exist_ok=True)
    clouds, first_poses = [], []
    for n, chunk in enumerate(fragment_chunks(frame_ids, frames_per_fragment)):
        idx = first_index + n
        colors, depths, poses = [], [], []
        for fid in chunk:
            cpath, dpath, ppath = frame_paths(layout.frame_prefix(scene, seq, fid))
            color = read_color(cpath)
            colors.append(color if K_color is None else color_to_depth_camera(color, K_color, K))
            depths.append(read_depth(dpath))
            poses.append(read_pose(ppath))
        pts, cols = fuse_frames(colors, depths, poses, K, fusion)
        if len(pts) == 0:
            raise DataError(layout.frame_prefix(scene, seq, chunk[0]),
                            f"fusing frames {chunk[0]}..{chunk[-1]} gave no points (all depth missing?)")
        order = np.lexsort((pts[:, 2], pts[:, 1], pts[:, 0]))  # deterministic bytes
        pts, cols = pts[order], cols[order]
        write_ply(layout.fragment(scene, idx), pts, cols)
        write_fragment_info(layout.fragment_info(scene, idx), FragmentInfo(scene, seq, chunk[0], chunk[-1]),
                            extra=f"# {len(chunk)} frames fused, tsdf voxel {fusion.tsdf_voxel} m\n")
        clouds.append(pts)
        first_poses.append(poses[0])
    return clouds, first_poses


def scene_pairs(
    scene: str, clouds: Sequence[np.ndarray], first_poses: Sequence[np.ndarray], cfg: PairConfig,
) -> tuple[list[PairRecord], list[float], list[np.ndarray]]:
    """Pairs i < j with overlap >= min_overlap, every pair's overlap, and the pairs' info matrices."""
    small = [voxel_downsample(c, cfg.overlap_voxel) for c in clouds]
    trees = [cKDTree(s) for s in small]
    lo = [s.min(0) for s in small]
    hi = [s.max(0) for s in small]
    n = len(clouds)
    pairs, overlaps, infos = [], [], []
    for i in range(n):
        for j in range(i + 1, n):
            T_ji = invert(first_poses[i]) @ first_poses[j]
            corners = np.array([[x, y, z] for x in (lo[j][0], hi[j][0]) for y in (lo[j][1], hi[j][1])
                                for z in (lo[j][2], hi[j][2])])
            cj = corners @ T_ji[:3, :3].T + T_ji[:3, 3]
            if np.any(cj.max(0) < lo[i] - cfg.overlap_radius) or np.any(cj.min(0) > hi[i] + cfg.overlap_radius):
                overlaps.append(0.0)
                continue
            ov = overlap_ratio(small[i], small[j], T_ji, cfg.overlap_radius, tree_i=trees[i])
            overlaps.append(ov)
            if ov >= cfg.min_overlap:
                pairs.append(PairRecord(scene, i, j, T_ji, ov, n))
                infos.append(info_matrix(small[i], small[j], T_ji, cfg.overlap_radius, seed=i * 100003 + j))
    return pairs, overlaps, infos


def build_scene(
    layout: Layout, scene: str, seq: str, frame_ids: Sequence[int], frames_per_fragment: int,
    fusion: FusionConfig, pair_cfg: PairConfig, is_test: bool,
) -> SceneResult:
    """Fuse one scene's sequence and write its benchmark files (test scenes)."""
    clouds, first_poses = fuse_sequence(layout, scene, seq, frame_ids, frames_per_fragment, fusion)
    pairs, overlaps, infos = scene_pairs(scene, clouds, first_poses, pair_cfg)
    res = SceneResult(scene, len(clouds), [len(c) for c in clouds], pairs, overlaps)
    if is_test:
        n = len(clouds)
        # like the official files, gt_overlap.log lists every pair i < j of the scene
        every = [PairRecord(scene, i, j, np.eye(4), ov, n)
                 for (i, j), ov in zip(((i, j) for i in range(n) for j in range(i + 1, n)), overlaps)]
        for bench in BENCHMARKS:
            sel = [k for k, p in enumerate(pairs) if benchmark_of(p.overlap, pair_cfg) == bench]
            d = layout.benchmark_dir(bench, scene)
            d.mkdir(parents=True, exist_ok=True)
            write_gt_log(d / "gt.log", [pairs[k] for k in sel])
            write_gt_info(d / "gt.info", [pairs[k] for k in sel], [infos[k] for k in sel])
            write_gt_overlap(d / "gt_overlap.log", every)
            res.benchmark_counts[bench] = len(sel)
    return res
