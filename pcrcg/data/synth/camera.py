"""Hand-held-like camera paths inside a room.

The operator walks a wobbly loop around the room centre at chest-to-eye height, looking across
the room at a point that wanders over the far side at furniture height (so views hold walls,
floor and furniture rather than a blank wall at arm's length), with slow roll drift and small
per-frame shake. The view turns by ``yaw_per_frame`` on average, so the overlap between two
fragments falls with their distance along the sequence and rises again when the loop comes back.
"""

from __future__ import annotations

import numpy as np

from pcrcg.data.synth.scene import Room
from pcrcg.geometry import look_at


def _smooth(rng: np.random.Generator, t: np.ndarray, period: float, n: int = 3) -> np.ndarray:
    """Smooth zero-mean noise of unit-ish amplitude, dominant period ``period`` (in t's units)."""
    out = np.zeros_like(t, dtype=np.float64)
    for k in range(n):
        f = rng.uniform(0.6, 1.6) * (2**k) / period
        out += rng.normal() / (2**k) * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return out / 1.3


def camera_path(room: Room, n_frames: int, yaw_per_frame_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Camera-to-world poses (n_frames, 4, 4) of a hand-held scan of ``room``."""
    W, D, H = room.size
    t = np.arange(n_frames, dtype=np.float64)
    yaw_rate = np.radians(yaw_per_frame_deg) * rng.choice([-1.0, 1.0])
    frames_per_turn = 2 * np.pi / max(abs(yaw_rate), 1e-6)
    # walk: an ellipse around the centre, at the pace the view turns
    rx, ry = max(0.2, W / 2 - 0.9) * rng.uniform(0.6, 1.0), max(0.2, D / 2 - 0.9) * rng.uniform(0.6, 1.0)
    phi = rng.uniform(0, 2 * np.pi) + yaw_rate * t + 0.3 * _smooth(rng, t, frames_per_turn / 2)
    x = W / 2 + rx * np.cos(phi) + 0.12 * _smooth(rng, t, frames_per_turn / 3)
    y = D / 2 + ry * np.sin(phi) + 0.12 * _smooth(rng, t, frames_per_turn / 3)
    z = rng.uniform(1.35, 1.7) + 0.08 * _smooth(rng, t, frames_per_turn / 2)
    x = np.clip(x, 0.8, W - 0.8)
    y = np.clip(y, 0.8, D - 0.8)
    # look across the room: at a point wandering on the far side of the centre, at furniture height
    swing = phi + np.pi + 0.6 * _smooth(rng, t, frames_per_turn / 2)
    reach = rng.uniform(0.3, 1.0) + 0.3 * _smooth(rng, t, frames_per_turn / 3)
    tx = W / 2 + reach * np.cos(swing) * min(1.0, W / D)
    ty = D / 2 + reach * np.sin(swing) * min(1.0, D / W)
    tz = np.clip(0.7 + 0.4 * _smooth(rng, t, frames_per_turn / 1.5), 0.1, 1.4)
    roll = np.radians(3.0) * _smooth(rng, t, frames_per_turn / 4)
    shake = rng.normal(0, 0.002, size=(n_frames, 3))
    poses = np.empty((n_frames, 4, 4))
    zz = np.broadcast_to(z, t.shape)
    for k in range(n_frames):
        eye = np.array([x[k], y[k], zz[k]]) + shake[k]
        poses[k] = look_at(eye, [tx[k], ty[k], tz[k]], up=(0.0, 0.0, 1.0), roll=roll[k])
    return poses
