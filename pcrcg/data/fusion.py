"""TSDF fusion of RGB-D frames into a fragment, as 3DMatch made its fragments.

Uses Open3D's tensor ``VoxelBlockGrid`` (sparse voxel blocks). Two traps measured on open3d-cpu
0.20: the legacy ``ScalableTSDFVolume`` returns empty clouds here, and ``VoxelBlockGrid`` returns an
empty cloud when fewer frames than its default ``weight_threshold`` (3.0) see a surface, so the
threshold is explicit. ``UniformTSDFVolume`` also works but costs 70 ms a frame at 256^3.

Same frames, same bytes: the grid's points come out in hash-map order, which differs from process to
process, and Open3D's ``voxel_down_sample`` sums each voxel's points in that order (float sums: the
averaged fragments differed by ~2e-7 m between two builds). The extracted points are therefore sorted
and voxel-averaged here in a fixed order (:func:`voxel_average`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from pcrcg.geometry import backproject, invert


@dataclass
class FusionConfig:
    tsdf_voxel: float = 0.015  # metres
    trunc_voxels: float = 4.0  # truncation distance in voxels
    depth_max: float = 4.5  # metres; farther depth is ignored
    min_weight: float = 1.0  # a voxel needs this many observations to become a point
    fragment_voxel: float = 0.01  # the fused cloud is voxel-averaged to this size (0 = off)
    block_count: int = 0  # hash-map capacity in 8^3-voxel blocks; 0 = estimated from the frames


def fuse_frames(
    colors: Sequence[np.ndarray],
    depths: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    K: np.ndarray,
    cfg: FusionConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Fuse frames into a cloud in the camera frame of the first frame.

    colors: (H, W, 3) uint8 each; depths: (H, W) float32 metres (0 = none); poses: (4, 4)
    camera-to-world each; K: (3, 3). Returns points (N, 3) float32 and colors (N, 3) float32 in [0, 1].
    """
    if not (len(colors) == len(depths) == len(poses)) or len(poses) == 0:
        raise ValueError("fuse_frames needs as many colors, depths and poses, at least one")
    import open3d as o3d  # here, not at the top: what reads data sets (a run) needs no Open3D
    import open3d.core as o3c
    world_to_frag = invert(poses[0])
    block_count = cfg.block_count or _estimate_blocks(depths, poses, world_to_frag, K, cfg)
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=cfg.tsdf_voxel,
        block_resolution=8,
        block_count=block_count,
    )
    Kt = o3c.Tensor(np.asarray(K, dtype=np.float64))
    integrated = 0
    for color, depth, pose in zip(colors, depths, poses):
        if color.shape[:2] != depth.shape:
            raise ValueError(f"color {color.shape[:2]} and depth {depth.shape} differ in size")
        if not np.any((depth > 0) & (depth < cfg.depth_max)):
            continue  # nothing in range (a blank wall at arm's length, a window): TSDF would abort
        mm = np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16)
        d_img = o3d.t.geometry.Image(o3c.Tensor(mm))
        c_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(color, dtype=np.uint8)))
        extrinsic = o3c.Tensor(invert(world_to_frag @ pose))  # fragment -> camera
        try:
            blocks = vbg.compute_unique_block_coordinates(
                d_img, Kt, extrinsic, 1000.0, cfg.depth_max, trunc_voxel_multiplier=cfg.trunc_voxels
            )
        except RuntimeError as exc:  # Open3D aborts on a frame whose few depths touch no block
            if "No block is touched" in str(exc):
                continue
            raise
        vbg.integrate(blocks, d_img, c_img, Kt, extrinsic, 1000.0, cfg.depth_max, trunc_voxel_multiplier=cfg.trunc_voxels)
        integrated += 1
    if integrated == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    # weights count observations (+1 per frame); the threshold is strict, hence the 0.5
    pcd = vbg.extract_point_cloud(weight_threshold=cfg.min_weight - 0.5)
    if pcd.is_empty():
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    pts = pcd.point.positions.numpy().astype(np.float32)
    cols = pcd.point.colors.numpy().astype(np.float32) if "colors" in pcd.point else np.zeros_like(pts)
    # a fixed order whatever the hash map's: by position, then color
    order = np.lexsort((*cols.T[::-1], pts[:, 2], pts[:, 1], pts[:, 0]))
    pts, cols = pts[order], cols[order]
    if cfg.fragment_voxel > 0:
        pts, cols = voxel_average(pts, cols, cfg.fragment_voxel)
    return pts, np.clip(cols, 0, 1)


def voxel_average(points: np.ndarray, colors: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Average points and colors per ``voxel``-sized cell, summing in the input order (deterministic,
    unlike a parallel reduction). (N, 3), (N, 3) -> (M, 3) float32 each, cells in key order.

    The cells are Open3D's (``floor(p / voxel)`` in float32), so the result is Open3D's
    ``voxel_down_sample`` up to the order of its float sums."""
    p32 = np.asarray(points, dtype=np.float32)
    keys = np.floor(p32 / np.float32(voxel)).astype(np.int64)
    p = p32.astype(np.float64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    sums = np.zeros((len(counts), 6))
    np.add.at(sums, inv, np.concatenate([p, np.asarray(colors, dtype=np.float64)], axis=1))
    mean = sums / counts[:, None]
    return mean[:, :3].astype(np.float32), mean[:, 3:].astype(np.float32)


def _estimate_blocks(depths, poses, world_to_frag, K, cfg: FusionConfig) -> int:
    """Blocks the truncation band will touch: unique blocks of the back-projected points, x8 margin.

    Allocating a fixed large hash map (60k blocks ~ 600 MB) cost more than fusing small fragments.
    """
    block = 8 * cfg.tsdf_voxel
    keys = []
    for depth, pose in zip(depths, poses):
        d = np.where(depth <= cfg.depth_max, depth, 0)
        pts, _ = backproject(d, K, stride=4)
        if len(pts):
            T = world_to_frag @ pose
            keys.append(np.floor((pts @ T[:3, :3].T + T[:3, 3]) / block).astype(np.int64))
    n = len(np.unique(np.concatenate(keys), axis=0)) if keys else 1
    return int(max(1000, 8 * n))
