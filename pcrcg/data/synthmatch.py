"""SynthMatch: the generated RGB-D registration benchmark in the 3DMatch layout.

Per scene: a random furnished room (:mod:`pcrcg.data.synth.scene`), a hand-held scan at real
speeds (:mod:`pcrcg.data.synth.camera`), frames ray-cast with a Kinect-like depth sensor and a
consumer colour camera (auto-exposure, motion blur, noise, JPEG; :mod:`pcrcg.data.synth.render`)
and written as PNGs in the 3DMatch RGB-D layout; then the same
fusion and pairing code as real data (:mod:`pcrcg.data.build`). Scenes are independent and seeded
by ``(seed, scene index)``, so they are generated in parallel and the output does not depend on
the number of workers.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from pcrcg.data.build import SceneResult, build_scene
from pcrcg.data.fusion import FusionConfig
from pcrcg.data.layout import Layout, write_color, write_depth, write_matrix
from pcrcg.errors import DataError
from pcrcg.data.pairs import PairConfig
from pcrcg.data.synth.camera import ScanConfig, ScanPath, _smooth
from pcrcg.data.synth.render import RoomRenderer, SensorModel
from pcrcg.data.synth.scene import make_room
from pcrcg.geometry import scale_intrinsics

K_640 = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])  # 7-Scenes / 3DMatch
SEQ = "seq-01"


@dataclass
class SynthConfig:
    n_scenes: int = 4
    n_val: int = 1
    n_test: int = 1
    width: int = 160
    height: int = 120
    fragments_per_scene: int = 8
    frames_per_fragment: int = 5
    # a fragment spans what 50 frames at 30 fps of a real scan span (3DMatch's fragments), however
    # many frames a profile renders of it
    fragment_seconds: float = 50 / 30
    walk_speed: float = 0.25  # m/s at most
    turn_rate_deg: float = 20.0  # deg/s the view turns on average
    inward_share: float = 0.5  # scans circling the central table (their fragments all overlap a lot)
    sweep_deg: float = 0.0  # back and forth along +-sweep_deg of the loop (camera.ScanConfig); 0: round it
    drift_deg_s: float = 2.0  # how fast the middle of that sweep moves on
    outward_radius: tuple[float, float] = (0.15, 0.35)  # outward loops' radius, share of the floor's reach
    shadows: bool = True


_PARENT_PID: int | None = None


def set_parent(pid: int) -> None:
    """Pool initializer: workers stop when the process that started them is gone (killed run)."""
    global _PARENT_PID
    _PARENT_PID = pid


def _orphaned() -> bool:
    return _PARENT_PID is not None and os.getppid() != _PARENT_PID


def scene_name(index: int) -> str:
    return f"synth-{index:03d}"


def assign_splits(n_scenes: int, n_val: int, n_test: int, seed: int) -> dict[str, list[str]]:
    """Scenes split by a seeded shuffle: test first, then val, the rest train (none: a test-only data set, as the
    real 3DMatch scene; a run that trains on it is refused by :func:`pcrcg.config.preflight`)."""
    if n_val + n_test > n_scenes:
        raise ValueError(f"n_scenes={n_scenes} is fewer than n_val={n_val} + n_test={n_test}")
    order = np.random.default_rng([seed, 7919]).permutation(n_scenes)
    names = [scene_name(int(k)) for k in order]
    return {
        "test": sorted(names[:n_test]),
        "val": sorted(names[n_test : n_test + n_val]),
        "train": sorted(names[n_test + n_val :]),
    }


def intrinsics_for(width: int, height: int) -> np.ndarray:
    return scale_intrinsics(K_640, width / 640.0, height / 480.0)


def auto_exposure(previous: float | None, linear, dt: float, target: float = 0.18, tau: float = 0.4) -> float:
    """The camera's exposure gain after a frame of linear radiance (H, W, 3): it moves towards
    the gain that puts the image's mean at ``target`` with time constant ``tau`` seconds (so a
    bright window or a dark corner is over- or under-exposed for a moment, as on real frames)."""
    mean = float(np.mean(linear[linear.shape[0] // 4 : 3 * linear.shape[0] // 4])) + 1e-4
    want = float(np.clip(target / mean, 0.05, 20.0))
    if previous is None:
        return want
    a = 1.0 - np.exp(-dt / tau)
    return float(np.exp((1 - a) * np.log(previous) + a * np.log(want)))


MAX_ATTEMPTS = 5
MIN_DEPTH_SHARE = 0.1  # a fragment whose frames hold less depth than this on average is a bad scan


class BadScan(Exception):
    """A scan with a fragment that sees (almost) nothing in depth range: drawn again."""


def render_scene(layout: Layout, index: int, seed: int, cfg: SynthConfig, sensor: SensorModel) -> list[int]:
    """Render one scene's frames into ``<root>/rgbd/<scene>/seq-01``; returns the frame ids.

    A scan whose camera faces a surface closer than the sensor's range (or a window) for a whole
    fragment is drawn again, room and path, from the next seed of the scene (at most
    ``MAX_ATTEMPTS`` times): the result still depends only on ``(seed, index)``."""
    for attempt in range(MAX_ATTEMPTS):
        try:
            return _render_attempt(layout, index, seed, cfg, sensor, attempt)
        except BadScan as exc:
            last = exc
    raise DataError(layout.rgbd_dir(scene_name(index)), f"no usable scan in {MAX_ATTEMPTS} attempts ({last})")


def _render_attempt(layout: Layout, index: int, seed: int, cfg: SynthConfig, sensor: SensorModel,
                    attempt: int) -> list[int]:
    rng = np.random.default_rng([seed, index] if attempt == 0 else [seed, index, attempt])
    scene = scene_name(index)
    room = make_room(rng)
    n_frames = cfg.fragments_per_scene * cfg.frames_per_fragment
    dt = cfg.fragment_seconds / cfg.frames_per_fragment
    path = ScanPath(room, rng, ScanConfig(walk_speed=cfg.walk_speed, turn_rate_deg=cfg.turn_rate_deg,
                                          inward_share=cfg.inward_share, sweep_deg=cfg.sweep_deg,
                                          drift_deg_s=cfg.drift_deg_s,
                                          outward_radius=tuple(cfg.outward_radius)))
    times = np.arange(n_frames) * dt
    poses = path.pose(times)
    K = intrinsics_for(cfg.width, cfg.height)
    renderer = RoomRenderer(room, sensor)
    flicker = 1.0 + 0.04 * np.stack([_smooth(rng, times, 3.0) for _ in range(len(room.lights))], 1)
    seq_dir = layout.rgbd_dir(scene) / SEQ
    seq_dir.mkdir(parents=True, exist_ok=True)
    write_matrix(layout.intrinsics(scene), K)
    gain = None
    depth_share = np.zeros(n_frames)
    for k in range(n_frames):
        if _orphaned():
            raise SystemExit(f"parent process gone; stopping {scene}")
        rad = renderer.radiance(poses[k], K, cfg.width, cfg.height, flicker[k], shadows=cfg.shadows)
        gain = auto_exposure(gain, rad.linear, dt)
        blur = None
        if sensor.exposure_time > 0:
            half = 0.5 * sensor.exposure_time
            p0, p1 = path.pose(np.array([times[k] - half, times[k] + half]))
            blur = renderer.image_motion(p0, p1, K, rad.depth)
        color = renderer.expose(rad.linear, gain, rng, blur)
        depth = renderer.sensor_depth(rad, rng)
        depth_share[k] = float(np.mean(depth > 0))
        if (k + 1) % cfg.frames_per_fragment == 0:
            share = depth_share[k + 1 - cfg.frames_per_fragment : k + 1].mean()
            if share < MIN_DEPTH_SHARE:
                raise BadScan(f"fragment {k // cfg.frames_per_fragment} of attempt {attempt}: {share:.1%} of pixels with depth")
        prefix = layout.frame_prefix(scene, SEQ, k)
        write_color(str(prefix) + ".color.png", color)
        write_depth(str(prefix) + ".depth.png", depth)
        write_matrix(str(prefix) + ".pose.txt", poses[k])
    return list(range(n_frames))


def generate_scene(
    root: str, index: int, seed: int, cfg: SynthConfig, sensor: SensorModel, fusion: FusionConfig,
    pair_cfg: PairConfig, is_test: bool, frames_only: bool = False,
) -> SceneResult:
    """Render, fuse and pair one scene (a process-pool task); ``frames_only``: render its frames and stop (no
    fragments, pairs or benchmark files: what the 2D pretraining reads)."""
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    layout = Layout(root)
    frame_ids = render_scene(layout, index, seed, cfg, sensor)
    if frames_only:
        return SceneResult(scene_name(index), 0, [])
    return build_scene(layout, scene_name(index), SEQ, frame_ids, cfg.frames_per_fragment, fusion, pair_cfg, is_test)
