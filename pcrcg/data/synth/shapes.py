"""Primitive shapes as lists of textured :class:`~pcrcg.data.synth.scene.Panel` facets.

Every builder takes a placement ``M`` (4x4, object-to-room, z up) and builds the shape in its own
frame: x, y centred on the origin, standing on z = 0 unless said otherwise. Curved shapes are
faceted finely enough (8-24 sides) that a 2.5 cm fusion cannot tell the facets apart.
"""

from __future__ import annotations

import numpy as np

from pcrcg.data.synth.panel import Panel
from pcrcg.data.synth.textures import Texture


def placement(x: float, y: float, z: float = 0.0, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """4x4 object-to-room transform: rotate by roll (x), pitch (y), yaw (z), then translate."""
    cz, sz = np.cos(yaw), np.sin(yaw)
    cy, sy = np.cos(pitch), np.sin(pitch)
    cx, sx = np.cos(roll), np.sin(roll)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    M = np.eye(4)
    M[:3, :3] = Rz @ Ry @ Rx
    M[:3, 3] = (x, y, z)
    return M


def compose(M: np.ndarray, x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw: float = 0.0,
            pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """``M`` followed by a local placement (a part placed in its parent's frame)."""
    return M @ placement(x, y, z, yaw, pitch, roll)


def _quad(M: np.ndarray, o, u, v, tex: Texture, kind: str) -> Panel:
    R, t = M[:3, :3], M[:3, 3]
    return Panel(R @ np.asarray(o, float) + t, R @ np.asarray(u, float), R @ np.asarray(v, float), tex, kind)


def _tri(M: np.ndarray, a, b, c, tex: Texture, kind: str) -> Panel:
    """Triangle a, b, c (counter-clockwise seen from its outside)."""
    a, b, c = (np.asarray(p, float) for p in (a, b, c))
    p = _quad(M, a, b - a, c - a, tex, kind)
    p.tri = True
    return p


def box(M: np.ndarray, size, tex: Texture, kind: str, bottom: bool = False, top: bool = True) -> list[Panel]:
    """A box of ``size`` (w, d, h): x in [-w/2, w/2], y in [-d/2, d/2], z in [0, h]."""
    w, d, h = (float(s) for s in size)
    x0, y0 = -w / 2, -d / 2
    X, Y, Z = np.array([w, 0, 0.0]), np.array([0, d, 0.0]), np.array([0, 0, h])
    out = [
        _quad(M, (x0, y0, 0), X, Z, tex, kind),  # -y
        _quad(M, (x0 + w, y0 + d, 0), -X, Z, tex, kind),  # +y
        _quad(M, (x0, y0 + d, 0), -Y, Z, tex, kind),  # -x
        _quad(M, (x0 + w, y0, 0), Y, Z, tex, kind),  # +x
    ]
    if top:
        out.append(_quad(M, (x0, y0, h), X, Y, tex, kind))
    if bottom:
        out.append(_quad(M, (x0, y0 + d, 0), X, -Y, tex, kind))
    return out


def frustum(M: np.ndarray, r0: float, r1: float, h: float, n: int, tex: Texture, kind: str,
            top: bool = True, bottom: bool = False, phase: float = 0.0) -> list[Panel]:
    """A faceted cone frustum (radius ``r0`` at z = 0, ``r1`` at z = h): cylinders, bins, lamp
    shades, bottles. Caps are triangle fans."""
    ang = phase + 2 * np.pi * np.arange(n + 1) / n
    c, s = np.cos(ang), np.sin(ang)
    lo = np.stack([r0 * c, r0 * s, np.zeros(n + 1)], 1)
    hi = np.stack([r1 * c, r1 * s, np.full(n + 1, h)], 1)
    out = []
    for k in range(n):
        out.append(_tri(M, lo[k], lo[k + 1], hi[k + 1], tex, kind))
        out.append(_tri(M, lo[k], hi[k + 1], hi[k], tex, kind))
    if top and r1 > 0:
        for k in range(n):
            out.append(_tri(M, (0, 0, h), hi[k], hi[k + 1], tex, kind))
    if bottom and r0 > 0:
        for k in range(n):
            out.append(_tri(M, (0, 0, 0), lo[k + 1], lo[k], tex, kind))
    return out


def ellipsoid(M: np.ndarray, radii, n_lat: int, n_lon: int, tex: Texture, kind: str, z_min: float = -1.0) -> list[Panel]:
    """A faceted ellipsoid centred on the origin; ``z_min`` in [-1, 1] cuts it below (a cushion, a
    dome, a plant's crown). Facets are triangles."""
    a, b, c = (float(r) for r in radii)
    th = np.linspace(np.arccos(np.clip(z_min, -1, 1)), 0.0, n_lat + 1)  # from the bottom up
    ph = np.linspace(0, 2 * np.pi, n_lon + 1)
    T, P = np.meshgrid(th, ph, indexing="ij")
    V = np.stack([a * np.sin(T) * np.cos(P), b * np.sin(T) * np.sin(P), c * np.cos(T)], -1)
    out = []
    for i in range(n_lat):
        for j in range(n_lon):
            p00, p01, p10, p11 = V[i, j], V[i, j + 1], V[i + 1, j], V[i + 1, j + 1]
            if np.linalg.norm(np.cross(p01 - p00, p11 - p00)) > 1e-9:
                out.append(_tri(M, p00, p01, p11, tex, kind))
            if np.linalg.norm(np.cross(p11 - p00, p10 - p00)) > 1e-9:
                out.append(_tri(M, p00, p11, p10, tex, kind))
    return out


def leaves(M: np.ndarray, rng: np.random.Generator, n: int, radius: float, height: float, size: float,
           tex: Texture, kind: str = "plant") -> list[Panel]:
    """``n`` leaf-like triangles scattered in a crown of ``radius`` around (0, 0, height)."""
    out = []
    for _ in range(n):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d) + 1e-9
        d[2] = abs(d[2]) * 0.8
        base = np.array([0, 0, height]) + d * radius * rng.uniform(0.3, 1.0)
        tip = base + (d + rng.normal(0, 0.4, 3)) * size
        side = np.cross(d, rng.normal(size=3))
        side = side / (np.linalg.norm(side) + 1e-9) * size * rng.uniform(0.25, 0.5)
        mid = 0.5 * (base + tip)
        out.append(_tri(M, base, mid + side, tip, tex, kind))
        out.append(_tri(M, base, tip, mid - side, tex, kind))
    return out


def flat(M: np.ndarray, w: float, h: float, tex: Texture, kind: str) -> Panel:
    """A w x h rectangle in the object's x-z plane facing -y, lower-left corner at (-w/2, 0, 0)
    (a poster, a picture, a screen)."""
    return _quad(M, (-w / 2, 0, 0), (w, 0, 0), (0, 0, h), tex, kind)
