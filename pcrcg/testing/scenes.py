"""A tiny RGB-D scene with known geometry, ray cast in NumPy (a fixture for tests, benchmarks and the
figures drawn without data; never used by a run).

A textured box room (the camera is inside) holding one textured box that occludes part of the
walls. :func:`render` gives exact color and depth for any pinhole camera; :func:`make_pair`
builds a :class:`pcrcg.data.dataset.PairSample` the way the 3DMatch layout does: each fragment
fuses the depth of several frames (here: back-projection + the real fragment step's voxel averaging,
:func:`pcrcg.data.fusion.voxel_average`, instead of TSDF), lives in the frame of its first camera,
and carries the first, last and middle frames as views.

The room is ray cast, not sampled: it is not the point room of :mod:`pcrcg.testing.rooms`. The cameras
pan from a chosen standpoint (:func:`pan_path`) rather than walk the real generator's hand-held path
(:func:`pcrcg.data.synth.camera.camera_path`, a random walk through a panel ``Room``), so that the
two fragments' overlap is fixed by construction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pcrcg.geometry import backproject, invert, look_at, transform_points


def _texture(rng: np.random.Generator, n: int = 256) -> np.ndarray:
    """A colorful, non-repetitive texture (n, n, 3) float32 in [0, 1]: multi-scale noise + patches."""
    from scipy.ndimage import gaussian_filter

    tex = np.zeros((n, n, 3), np.float32)
    for sigma, amp in ((1.0, 0.25), (3.0, 0.45), (9.0, 0.6)):
        noise = gaussian_filter(rng.random((n, n, 3)).astype(np.float32), sigma=(sigma, sigma, 0))
        noise = (noise - noise.mean()) / (noise.std() + 1e-6)
        tex += amp * noise
    tex = 0.5 + 0.18 * tex
    for _ in range(14):  # posters: flat rectangles with a distinct color
        h, w = rng.integers(n // 16, n // 5, size=2)
        y, x = rng.integers(0, n - h), rng.integers(0, n - w)
        tex[y : y + h, x : x + w] = 0.6 * rng.random(3) + 0.4 * tex[y : y + h, x : x + w]
    return np.clip(tex, 0.0, 1.0)


@dataclass
class ToyRoom:
    """Axis-aligned room ``[0, size]`` (metres, z up) and one box ``box_min..box_max`` inside it."""

    size: tuple[float, float, float] = (6.0, 5.0, 3.0)
    box_min: tuple[float, float, float] = (3.4, 2.9, 0.0)
    box_max: tuple[float, float, float] = (4.2, 3.7, 1.3)
    texel: float = 0.02  # metres per texel
    seed: int = 0
    textures: list[np.ndarray] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        if not self.textures:
            rng = np.random.default_rng(self.seed)
            self.textures = [_texture(rng) for _ in range(7)]  # 6 room faces + the box

    def _shade(self, pts: np.ndarray, face: np.ndarray) -> np.ndarray:
        """Colors (N, 3) of surface points given face ids (0..5 room: axis*2+side, 6 box)."""
        from scipy.ndimage import map_coordinates

        out = np.zeros((len(pts), 3), np.float32)
        for f in np.unique(face):
            sel = face == f
            p = pts[sel]
            axis = 0 if f == 6 else f // 2
            if f == 6:  # box: use the two coordinates tangent to the hit face (largest normal comp.)
                c = 0.5 * (np.array(self.box_min) + np.array(self.box_max))
                h = 0.5 * (np.array(self.box_max) - np.array(self.box_min))
                rel = np.abs((p - c) / h)
                ax = np.argmax(rel, axis=1)
                a0 = np.where(ax == 0, p[:, 1], p[:, 0])
                a1 = np.where(ax == 2, p[:, 1], p[:, 2]) + ax * 1.7
            else:
                others = [k for k in range(3) if k != axis]
                a0, a1 = p[:, others[0]], p[:, others[1]]
            tex = self.textures[int(f)]
            n = tex.shape[0]
            r = (a1 / self.texel) % n
            c = (a0 / self.texel) % n
            for ch in range(3):
                out[sel, ch] = map_coordinates(tex[..., ch], [r, c], order=1, mode="grid-wrap")
        return out

    def face_of(self, pts: np.ndarray) -> np.ndarray:
        """Face id (N,) of surface points: the nearest room plane or the box (6)."""
        size = np.array(self.size)
        d_room = np.concatenate([np.abs(pts), np.abs(pts - size)], axis=1)  # (N, 6): lo x,y,z, hi x,y,z
        order = [0, 3, 1, 4, 2, 5]  # -> face ids axis*2 + side
        d_room = d_room[:, order]
        c = 0.5 * (np.array(self.box_min) + np.array(self.box_max))
        h = 0.5 * (np.array(self.box_max) - np.array(self.box_min))
        q = np.abs(pts - c) - h
        d_box = np.abs(np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0))
        face = np.argmin(d_room, axis=1)
        return np.where(d_box < d_room.min(axis=1), 6, face)

    def raycast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray parameter t of the first hit (N,) and the face id (N,) for rays o + t d (o inside)."""
        size = np.array(self.size)
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = np.where(dirs > 0, size, 0.0)
            t_ax = (bound - origins) / dirs
        t_ax = np.where(np.isfinite(t_ax) & (t_ax > 0), t_ax, np.inf)
        ax = np.argmin(t_ax, axis=1)
        t = t_ax[np.arange(len(t_ax)), ax]
        face = ax * 2 + (dirs[np.arange(len(dirs)), ax] > 0)
        bmin, bmax = np.array(self.box_min), np.array(self.box_max)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (bmin - origins) / dirs
            t2 = (bmax - origins) / dirs
        tn = np.nanmax(np.minimum(t1, t2), axis=1)
        tf = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (tn <= tf) & (tn > 1e-6) & (tn < t)
        t = np.where(hit, tn, t)
        face = np.where(hit, 6, face)
        return t, face


def toy_intrinsics(width: int = 160, height: int = 120, fov_deg: float = 70.0) -> np.ndarray:
    """Pinhole intrinsics with a horizontal field of view ``fov_deg`` and the principal point centred."""
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


def render(room: ToyRoom, cam_to_world: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Color (H, W, 3) uint8 and depth (H, W) float32 metres (camera z) of the room seen by a camera."""
    v, u = np.mgrid[0:height, 0:width]
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1).reshape(-1, 3)
    R, t = cam_to_world[:3, :3], cam_to_world[:3, 3]
    dirs = rays_cam @ R.T  # camera z = 1 so the ray parameter is the depth
    origins = np.broadcast_to(t, dirs.shape)
    depth, face = room.raycast(origins, dirs)
    pts = origins + depth[:, None] * dirs
    color = room._shade(pts, face)
    color = np.clip(np.round(color * 255), 0, 255).astype(np.uint8).reshape(height, width, 3)
    return color, depth.astype(np.float32).reshape(height, width)


def pan_path(eye: np.ndarray, yaw0_deg: float, yaw1_deg: float, n: int, pitch_deg: float = -8.0,
                step: np.ndarray | None = None) -> list[np.ndarray]:
    """``n`` camera-to-world poses panning from yaw0 to yaw1 (degrees, about z) while moving by ``step``."""
    eye = np.asarray(eye, float)
    step = np.zeros(3) if step is None else np.asarray(step, float)
    out = []
    for k, yaw in enumerate(np.linspace(yaw0_deg, yaw1_deg, n)):
        e = eye + k * step
        y, p = np.radians(yaw), np.radians(pitch_deg)
        target = e + np.array([np.cos(y) * np.cos(p), np.sin(y) * np.cos(p), np.sin(p)])
        out.append(look_at(e, target, up=(0.0, 0.0, 1.0)))
    return out


@dataclass
class ToyFragment:
    points: np.ndarray  # (N, 3) float32 in the fragment frame (= first camera)
    colors: np.ndarray  # (N, 3) float32 in [0, 1]
    views: list  # list[View] first, last, middle; pose camera-to-fragment
    first_pose: np.ndarray  # camera-to-world of the first frame


def make_fragment(room: ToyRoom, poses: list[np.ndarray], K: np.ndarray, width: int, height: int,
                  voxel: float = 0.05, stride: int = 2, name: str = "toy") -> ToyFragment:
    """Fuse the frames seen from ``poses`` into a fragment and keep first/last/middle as views."""
    from pcrcg.data.dataset import View
    from pcrcg.data.fusion import voxel_average

    world_to_frag = invert(poses[0])
    frames = [render(room, P, K, width, height) for P in poses]
    pts = []
    for (color, depth), P in zip(frames, poses):
        p_cam, _ = backproject(depth, K, stride)
        pts.append(transform_points(world_to_frag @ P, p_cam))
    pts = np.concatenate(pts)
    points, _ = voxel_average(pts, np.zeros_like(pts), voxel)
    world = transform_points(poses[0], points.astype(np.float64))
    colors = room._shade(world, room.face_of(world))
    n = len(poses)
    views = []
    for k in (0, n - 1, (n - 1) // 2):
        color, depth = frames[k]
        views.append(View(color, depth, K.copy(), world_to_frag @ poses[k], k, f"<{name}:frame{k}>"))
    return ToyFragment(points, colors, views, poses[0])


def make_pair(seed: int = 0, width: int = 160, height: int = 120, frames: int = 5, voxel: float = 0.05,
              yaw_offset_deg: float = 35.0):
    """A :class:`PairSample` of two overlapping fragments of the toy room, with 3 views each.

    ``src`` pans from yaw 10+offset to 50+offset degrees, ``tgt`` from 10 to 50 (same standpoint
    give or take 10 cm), so the pair overlaps; ``transform`` maps src into tgt exactly.
    """
    from pcrcg.data.dataset import PairSample

    rng = np.random.default_rng(seed)
    room = ToyRoom(seed=seed)
    K = toy_intrinsics(width, height)
    eye = np.array([1.2, 1.0, 1.5]) + rng.uniform(-0.1, 0.1, 3)
    tgt_poses = pan_path(eye, 10.0, 50.0, frames, step=[0.04, 0.0, 0.0])
    src_poses = pan_path(eye + [0.1, 0.05, 0.0], 10.0 + yaw_offset_deg, 50.0 + yaw_offset_deg, frames,
                            step=[0.0, 0.04, 0.0])
    tgt = make_fragment(room, tgt_poses, K, width, height, voxel, name=f"toy{seed}:tgt")
    src = make_fragment(room, src_poses, K, width, height, voxel, name=f"toy{seed}:src")
    T = invert(tgt.first_pose) @ src.first_pose
    return PairSample(
        scene=f"toy{seed}", i=0, j=1,
        src_points=src.points, tgt_points=tgt.points,
        src_colors=src.colors, tgt_colors=tgt.colors,
        transform=T, overlap=float("nan"),
        src_views=src.views, tgt_views=tgt.views,
    )
