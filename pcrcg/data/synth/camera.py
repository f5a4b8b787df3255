"""Hand-held scanning trajectories like 7-Scenes' and SUN3D's.

The operator walks slowly through the free part of the room (:attr:`Room.walkable`) along a
loop, either near the middle with the camera turned outwards to the walls and furniture, or
round the room's middle with the camera turned inwards to the tables there (as 7-Scenes'
kitchen was scanned), surfaces 1-3 m away, tilted down towards tables and floor, with the 6-DoF wobble of a
hand: slow swings of the gaze (left-right and up-down), roll, height changes, pauses, and a
tremor at the frame rate. The path is a smooth function of time, so poses can be read at any
instant: the camera's pose during an exposure gives the motion blur.

Speeds are those of real scans: about 0.15-0.35 m/s walking and 10-30 deg/s turning; a
3DMatch fragment (50 frames at 30 fps) spans 1.7 s of it. With ``sweep_deg`` the operator goes
back and forth along an arc of the loop instead of round it (``ScanConfig``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcrcg.data.synth.panel import Room
from pcrcg.geometry import look_at


def _smooth(rng: np.random.Generator, t: np.ndarray, period: float, n: int = 3) -> np.ndarray:
    """Smooth zero-mean noise of unit-ish amplitude, dominant period ``period`` (in t's units)."""
    out = np.zeros_like(np.asarray(t, dtype=np.float64))
    for k in range(n):
        f = rng.uniform(0.6, 1.6) * (2**k) / period
        out = out + rng.normal() / (2**k) * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return out / 1.3


class _Smooth:
    """A frozen draw of :func:`_smooth`: the same curve at any times."""

    def __init__(self, rng: np.random.Generator, period: float, n: int = 3):
        self.f = np.array([rng.uniform(0.6, 1.6) * (2**k) / period for k in range(n)])
        self.a = np.array([rng.normal() / (2**k) for k in range(n)]) / 1.3
        self.p = rng.uniform(0, 2 * np.pi, n)

    def __call__(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        return np.sum(self.a * np.sin(2 * np.pi * self.f * t[..., None] + self.p), -1)


@dataclass
class ScanConfig:
    walk_speed: float = 0.25  # m/s along the loop at most
    turn_rate_deg: float = 20.0  # deg/s the view turns on average
    pitch_deg: float = -28.0  # mean tilt (down)
    gaze_swing_deg: float = 15.0  # amplitude of left-right looks
    height: tuple[float, float] = (1.25, 1.65)
    tremor: float = 0.003  # m, hand shake
    inward_share: float = 0.5  # share of scans that circle the central table, looking inwards
    # back and forth: the operator sweeps along an arc of +-sweep_deg of the loop (slowing at its
    # ends) whose middle drifts at drift_deg_s, as real scans go over the same counters again from
    # about the same side; 0: round and round the loop (generator v5, whose low-overlap pairs were
    # mostly the two sides of a table or room: median relative rotation 110-120 deg against real
    # 3DLoMatch's 52 deg)
    sweep_deg: float = 0.0
    drift_deg_s: float = 2.0
    # outward scans: the loop's radius as a share of the free floor's reach from the middle (drawn
    # in this range); larger loops translate more along a sweep (real 3DLoMatch pairs: 1.6 m apart)
    outward_radius: tuple[float, float] = (0.15, 0.35)
    # inward scans: the distance from the table's middle (drawn in this range, at most 80% of the free
    # floor's reach) and the extra tilt down towards it. Generator v7: the camera stands as far from
    # what it scans as in 7-Scenes' kitchen (median depth per frame, p10 / p50 / p90: real seq-01
    # 1.42 / 1.84 / 2.42 m; v6, 1.2-1.8 m and 10 deg more tilt: inward scans 0.91 / 1.38 / 2.16, all
    # scans 1.15 / 1.69 / 2.14; v7 with the cpu profile's loops: 1.31 / 1.79 / 2.30, first 10 scenes),
    # as fragments seen from closer hold fewer points (v6: 12.7k at 2.5 cm, real 19.6k)
    inward_radius: tuple[float, float] = (1.6, 2.2)
    inward_tilt_deg: float = 0.0


class ScanPath:
    """A hand-held scan of ``room``: ``pose(t)`` is the camera-to-world pose at time t (s)."""

    def __init__(self, room: Room, rng: np.random.Generator, cfg: ScanConfig | None = None):
        self.cfg = cfg = cfg or ScanConfig()
        walk = room.walkable if room.walkable is not None else None
        cell = room.cell
        if walk is None or walk.sum() < 4:
            W, D = room.size[:2]
            xs, ys = np.meshgrid(np.arange(0.8, W - 0.8, 0.1), np.arange(0.8, D - 0.8, 0.1), indexing="ij")
            pts = np.stack([xs.ravel(), ys.ravel()], 1) if xs.size else np.array([[W / 2, D / 2]])
        else:
            ix, iy = np.nonzero(walk)
            pts = (np.stack([ix, iy], 1) + 0.5) * cell
        self.inward = bool(room.focus is not None and rng.random() < cfg.inward_share)
        self.center = np.asarray(room.focus, float) if self.inward else pts.mean(0)
        # the loop: per direction, a radius inside the free space (70-85% of its reach)
        ang = np.arctan2(pts[:, 1] - self.center[1], pts[:, 0] - self.center[0])
        dist = np.linalg.norm(pts - self.center, axis=1)
        bins = 36
        b = ((ang + np.pi) / (2 * np.pi) * bins).astype(int) % bins
        reach = np.zeros(bins)
        for k in range(bins):
            reach[k] = np.percentile(dist[b == k], 90) if np.any(b == k) else 0.0
        reach = np.maximum(reach, 0.05)
        kern = np.array([0.1, 0.2, 0.4, 0.2, 0.1])
        reach = np.convolve(np.concatenate([reach[-2:], reach, reach[:2]]), kern, "valid")  # circular smoothing
        # inwards: round the table at arm's length beyond its edge; outwards: near the middle
        self.reach = np.minimum(reach * 0.8, rng.uniform(*cfg.inward_radius)) if self.inward else reach * rng.uniform(*cfg.outward_radius)
        self.pts = pts
        self.direction = float(rng.choice([-1.0, 1.0]))
        self.theta0 = rng.uniform(0, 2 * np.pi)
        perim = 2 * np.pi * max(0.3, float(np.mean(self.reach)))
        self.omega = min(np.radians(cfg.turn_rate_deg), cfg.walk_speed / max(0.05, float(np.mean(self.reach))))
        self.perimeter = perim
        self.s_speed = _Smooth(rng, 12.0)
        self.s_gaze = _Smooth(rng, 9.0)
        self.s_pitch = _Smooth(rng, 7.0)
        self.s_height = _Smooth(rng, 10.0)
        self.s_roll = _Smooth(rng, 5.0)
        self.s_wob = [_Smooth(rng, 6.0) for _ in range(2)]
        self.s_tremor = [_Smooth(rng, 0.35, n=2) for _ in range(3)]
        self.h0 = rng.uniform(*cfg.height)

    def _theta(self, t: np.ndarray) -> np.ndarray:
        # progress with a varying pace (never backwards): integral of omega * (1 + 0.6 s(t))
        u = self.omega * (t + 0.6 * self._integral(self.s_speed, t))
        if self.cfg.sweep_deg <= 0:
            return self.theta0 + self.direction * u
        a = np.radians(self.cfg.sweep_deg)
        middle = self.theta0 + self.direction * np.radians(self.cfg.drift_deg_s) * t
        return middle + self.direction * a * np.sin(u / a)

    @staticmethod
    def _integral(s: _Smooth, t: np.ndarray) -> np.ndarray:
        w = 2 * np.pi * s.f
        return np.sum(s.a / w * (np.cos(s.p) - np.cos(w * np.asarray(t)[..., None] + s.p)), -1)

    def _radius(self, theta: np.ndarray) -> np.ndarray:
        bins = len(self.reach)
        x = ((theta + np.pi) / (2 * np.pi) * bins) % bins
        k0 = np.floor(x).astype(int) % bins
        f = x - np.floor(x)
        return self.reach[k0] * (1 - f) + self.reach[(k0 + 1) % bins] * f

    def pose(self, t) -> np.ndarray:
        """Camera-to-world poses (..., 4, 4) at times ``t`` (s)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        cfg = self.cfg
        th = self._theta(t)
        r = self._radius(th)
        x = self.center[0] + r * np.cos(th) + 0.08 * self.s_wob[0](t)
        y = self.center[1] + r * np.sin(th) + 0.08 * self.s_wob[1](t)
        z = self.h0 + 0.08 * self.s_height(t)
        tremor = np.stack([s(t) for s in self.s_tremor], -1) * cfg.tremor
        # gaze outwards (radially), swinging left and right, tilted down
        yaw = th + (np.pi if self.inward else 0.0) + np.radians(cfg.gaze_swing_deg) * self.s_gaze(t)
        pitch = np.radians(cfg.pitch_deg - (cfg.inward_tilt_deg if self.inward else 0.0)) + np.radians(10.0) * self.s_pitch(t)
        roll = np.radians(4.0) * self.s_roll(t)
        out = np.empty(t.shape + (4, 4))
        for k in range(len(t)):
            eye = np.array([x[k], y[k], z[k]]) + tremor[k]
            d = np.array([np.cos(yaw[k]) * np.cos(pitch[k]), np.sin(yaw[k]) * np.cos(pitch[k]), np.sin(pitch[k])])
            out[k] = look_at(eye, eye + d, up=(0.0, 0.0, 1.0), roll=roll[k])
        return out


def camera_path(room: Room, n_frames: int, frame_dt: float, rng: np.random.Generator,
                cfg: ScanConfig | None = None) -> np.ndarray:
    """Camera-to-world poses (n_frames, 4, 4) of a hand-held scan of ``room``, one every
    ``frame_dt`` seconds."""
    return ScanPath(room, rng, cfg).pose(np.arange(n_frames) * frame_dt)
