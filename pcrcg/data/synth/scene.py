"""Procedural indoor rooms made of textured rectangles ("panels").

A room is a box (floor, ceiling, four walls) holding furniture-like solids (wall units, tables
with legs, low boxes, clutter on tables, columns and pipes by the walls, objects on the floor; many
turned off the room's axes so that low-overlap pairs are not made of interchangeable right angles)
and flat textured posters and rugs a few millimetres in
front of walls and floor: surfaces where geometry is ambiguous and color is not.

Coordinates: metres, z up, the room spans [0, W] x [0, D] x [0, H].
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pcrcg.data.synth.textures import Texture, random_texture


@dataclass
class Panel:
    """A textured rectangle: ``origin + s * axis_u + t * axis_v`` for s, t in [0, 1]."""

    origin: np.ndarray  # (3,)
    axis_u: np.ndarray  # (3,) edge vector (length = width)
    axis_v: np.ndarray  # (3,) edge vector (length = height)
    texture: Texture
    kind: str

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.axis_u, self.axis_v)
        return n / np.linalg.norm(n)


@dataclass
class Room:
    size: np.ndarray  # (3,) W, D, H
    panels: list[Panel] = field(default_factory=list)
    lights: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (L, 3) positions
    light_power: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (L,)
    ambient: float = 0.3
    keepout: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # boxes (min, max)

    def mesh_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (4P, 3) float32 and triangles (2P, 3) int32; triangle 2p, 2p+1 belong to panel p."""
        verts, tris = [], []
        for p, pan in enumerate(self.panels):
            o, a, b = pan.origin, pan.axis_u, pan.axis_v
            verts += [o, o + a, o + a + b, o + b]
            k = 4 * p
            tris += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
        return np.asarray(verts, np.float32), np.asarray(tris, np.int32)


def _box_panels(lo: np.ndarray, hi: np.ndarray, tex: Texture, kind: str, skip_bottom: bool = True) -> list[Panel]:
    """Outward-facing faces of an axis-aligned box (the bottom face is skipped by default)."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    dx, dy, dz = hi - lo
    X, Y, Z = np.eye(3)
    faces = [
        Panel(np.array([x0, y0, z1]), X * dx, Y * dy, tex, kind),  # top, normal +z
        Panel(np.array([x0, y0, z0]), X * dx, Z * dz, tex, kind),  # normal -y
        Panel(np.array([x1, y1, z0]), -X * dx, Z * dz, tex, kind),  # normal +y
        Panel(np.array([x0, y1, z0]), -Y * dy, Z * dz, tex, kind),  # normal -x
        Panel(np.array([x1, y0, z0]), Y * dy, Z * dz, tex, kind),  # normal +x
    ]
    if not skip_bottom:
        faces.append(Panel(np.array([x0, y1, z0]), X * dx, -Y * dy, tex, kind))
    return faces


def _yawed_box_panels(center: np.ndarray, size: np.ndarray, z0: float, yaw: float, tex: Texture,
                      kind: str) -> tuple[list[Panel], np.ndarray, np.ndarray]:
    """A box of ``size`` (w, d, h) standing at height ``z0``, turned by ``yaw`` (rad) about z around
    ``center`` (x, y). Returns its five outward faces (top and sides) and its axis-aligned bounds."""
    c, s = np.cos(yaw), np.sin(yaw)
    u = np.array([c, s, 0.0]) * size[0]
    v = np.array([-s, c, 0.0]) * size[1]
    Z = np.array([0.0, 0.0, size[2]])
    o = np.array([center[0], center[1], z0]) - 0.5 * (u + v)
    panels = [
        Panel(o + Z, u, v, tex, kind),  # top, normal +z
        Panel(o, u, Z, tex, kind),  # normal -v
        Panel(o + u + v, -u, Z, tex, kind),  # normal +v
        Panel(o + v, -v, Z, tex, kind),  # normal -u
        Panel(o + u, v, Z, tex, kind),  # normal +u
    ]
    corners = np.stack([o, o + u, o + v, o + u + v])
    lo = np.array([*corners[:, :2].min(0), z0])
    hi = np.array([*corners[:, :2].max(0), z0 + size[2]])
    return panels, lo, hi


def _prism_panels(center: np.ndarray, radius: float, z0: float, z1: float, n_sides: int, phase: float,
                  tex: Texture, kind: str) -> list[Panel]:
    """The side faces of a regular ``n_sides``-gon prism (a column, a pipe) from ``z0`` to ``z1``."""
    ang = phase + 2 * np.pi * np.arange(n_sides + 1) / n_sides
    ring = np.stack([center[0] + radius * np.cos(ang), center[1] + radius * np.sin(ang), np.full(n_sides + 1, z0)], 1)
    up = np.array([0.0, 0.0, z1 - z0])
    # counter-clockwise ring seen from above: (edge, up) has an outward normal
    return [Panel(ring[k], ring[k + 1] - ring[k], up, tex, kind) for k in range(n_sides)]


def _overlaps(lo, hi, boxes, margin=0.05) -> bool:
    for blo, bhi in boxes:
        if np.all(lo[:2] < bhi[:2] + margin) and np.all(hi[:2] > blo[:2] - margin):
            return True
    return False


def make_room(rng: np.random.Generator) -> Room:
    """A random furnished room."""
    W, D = rng.uniform(3.5, 6.0, size=2)
    H = rng.uniform(2.5, 3.0)
    room = Room(size=np.array([W, D, H]))
    X, Y, Z = np.eye(3)
    wall_tex = random_texture(rng, "wall")
    # floor (normal +z), ceiling (normal -z), walls facing inward
    room.panels += [
        Panel(np.zeros(3), X * W, Y * D, random_texture(rng, "floor"), "floor"),
        Panel(np.array([0, D, H]), X * W, -Y * D, random_texture(rng, "ceiling"), "ceiling"),
        Panel(np.array([0, 0, 0]), Z * H, X * W, wall_tex, "wall"),  # y=0, normal +y
        Panel(np.array([W, D, 0]), Z * H, -X * W, wall_tex if rng.random() < 0.5 else random_texture(rng, "wall"), "wall"),
        Panel(np.array([0, D, 0]), Z * H, -Y * D, random_texture(rng, "wall"), "wall"),  # x=0, normal +x
        Panel(np.array([W, 0, 0]), Z * H, Y * D, wall_tex, "wall"),  # x=W, normal -x
    ]
    boxes: list[tuple[np.ndarray, np.ndarray]] = []

    # wall units: cabinets, shelves, wardrobes against the walls
    for _ in range(int(rng.integers(2, 6))):
        for _try in range(20):
            wall = int(rng.integers(0, 4))
            w, d, h = rng.uniform(0.6, 1.8), rng.uniform(0.3, 0.6), rng.uniform(0.7, 2.2)
            if wall in (0, 1):  # along x at y=0 or y=D
                x0 = rng.uniform(0.05, W - w - 0.05)
                y0 = 0.0 if wall == 0 else D - d
                lo, hi = np.array([x0, y0, 0]), np.array([x0 + w, y0 + d, h])
            else:
                y0 = rng.uniform(0.05, D - w - 0.05)
                x0 = 0.0 if wall == 2 else W - d
                lo, hi = np.array([x0, y0, 0]), np.array([x0 + d, y0 + w, h])
            if not _overlaps(lo, hi, boxes):
                boxes.append((lo, hi))
                room.panels += _box_panels(lo, hi, random_texture(rng, "furniture"), "furniture")
                if rng.random() < 0.7:  # a poster on the unit's front
                    _add_front_poster(room, rng, lo, hi, wall)
                break

    # interior: tables with legs and clutter, low boxes (sofas, beds, stools); all < 1.1 m high
    cx, cy = W / 2, D / 2
    for _ in range(int(rng.integers(2, 5))):
        for _try in range(20):
            w, d = rng.uniform(0.5, 1.8), rng.uniform(0.5, 1.2)
            x0 = rng.uniform(0.7, W - w - 0.7)
            y0 = rng.uniform(0.7, D - d - 0.7)
            lo2, hi2 = np.array([x0, y0, 0]), np.array([x0 + w, y0 + d, 0])
            if _overlaps(lo2, hi2, boxes, margin=0.3):
                continue
            tex = random_texture(rng, "furniture")
            if rng.random() < 0.55:  # table
                ht = rng.uniform(0.68, 0.8)
                top_lo, top_hi = np.array([x0, y0, ht - 0.04]), np.array([x0 + w, y0 + d, ht])
                room.panels += _box_panels(top_lo, top_hi, tex, "furniture", skip_bottom=False)
                leg = 0.05
                for lx, ly in ((x0, y0), (x0 + w - leg, y0), (x0, y0 + d - leg), (x0 + w - leg, y0 + d - leg)):
                    room.panels += _box_panels(np.array([lx, ly, 0]), np.array([lx + leg, ly + leg, ht - 0.04]), tex, "furniture")
                for _c in range(int(rng.integers(0, 4))):  # clutter on the table
                    s = rng.uniform(0.08, 0.35, size=3)
                    s[:2] = np.minimum(s[:2], [w * 0.45, d * 0.45])
                    px = rng.uniform(x0, x0 + w - s[0])
                    py = rng.uniform(y0, y0 + d - s[1])
                    room.panels += _box_panels(np.array([px, py, ht]), np.array([px + s[0], py + s[1], ht + s[2]]),
                                               random_texture(rng, "poster" if rng.random() < 0.4 else "furniture"), "furniture")
            elif rng.random() < 0.6:  # low solid turned off the room's axes (armchair, crate, bed)
                h = rng.uniform(0.35, 1.0)
                yaw = rng.uniform(-0.7, 0.7)
                faces, blo, bhi = _yawed_box_panels(np.array([x0 + w / 2, y0 + d / 2]), np.array([w, d, h]) * 0.8,
                                                    0.0, yaw, tex, "furniture")
                room.panels += faces
                if rng.random() < 0.5:  # something smaller on it, turned again
                    s2 = rng.uniform(0.15, 0.4, size=3)
                    faces2, _, _ = _yawed_box_panels(np.array([x0 + w / 2, y0 + d / 2]) + rng.uniform(-0.1, 0.1, 2), s2, h,
                                                     yaw + rng.uniform(-0.8, 0.8), random_texture(rng, "furniture"), "furniture")
                    room.panels += faces2
            else:  # low solid
                h = rng.uniform(0.35, 1.0)
                room.panels += _box_panels(np.array([x0, y0, 0]), np.array([x0 + w, y0 + d, h]), tex, "furniture")
                if rng.random() < 0.4:  # a second, smaller block on top (backrest, pillow)
                    h2 = rng.uniform(0.1, 0.3)
                    room.panels += _box_panels(np.array([x0, y0, h]), np.array([x0 + w, y0 + min(d, 0.25), min(h + h2, 1.1)]),
                                               random_texture(rng, "furniture"), "furniture")
            boxes.append((lo2, hi2 + np.array([0, 0, 1.1])))
            break

    # things that break the room's symmetry: columns and pipes by the walls, objects on the floor at
    # random angles (the camera walks >= 0.8 m from the walls and looks across the room)
    for _ in range(int(rng.integers(1, 4))):
        wall = int(rng.integers(0, 4))
        r = rng.uniform(0.06, 0.22)
        off = rng.uniform(r + 0.02, 0.6)
        along = rng.uniform(0.4, (W if wall in (0, 1) else D) - 0.4)
        c = {0: (along, off), 1: (along, D - off), 2: (off, along), 3: (W - off, along)}[wall]
        c = np.asarray(c)
        if _overlaps(c - r, c + r, boxes, margin=0.02):
            continue
        top = H if rng.random() < 0.6 else rng.uniform(0.8, 1.9)
        n_sides = int(rng.choice([4, 6, 8, 12]))
        room.panels += _prism_panels(c, r, 0.0, top, n_sides, rng.uniform(0, np.pi), random_texture(rng, "furniture"), "furniture")
        boxes.append((np.array([c[0] - r, c[1] - r, 0]), np.array([c[0] + r, c[1] + r, top])))
    for _ in range(int(rng.integers(3, 8))):
        for _try in range(10):
            size = np.array([rng.uniform(0.15, 0.6), rng.uniform(0.15, 0.6), rng.uniform(0.1, 0.7)])
            c = np.array([rng.uniform(0.4, W - 0.4), rng.uniform(0.4, D - 0.4)])
            faces, blo, bhi = _yawed_box_panels(c, size, 0.0, rng.uniform(0, np.pi / 2),
                                                random_texture(rng, "poster" if rng.random() < 0.3 else "furniture"), "furniture")
            if _overlaps(blo, bhi, boxes, margin=0.1):
                continue
            room.panels += faces
            boxes.append((blo, bhi))
            break

    # posters on the walls, rugs on the floor: flat, 3 mm off the surface
    for _ in range(int(rng.integers(5, 11))):
        wall = int(rng.integers(0, 4))
        w, h = rng.uniform(0.5, 1.8), rng.uniform(0.4, 1.3)
        z0 = rng.uniform(0.4, max(0.5, H - h - 0.2))
        eps = 0.003
        tex = random_texture(rng, "poster")
        if wall == 0:
            x0 = rng.uniform(0.1, W - w - 0.1)
            room.panels.append(Panel(np.array([x0, eps, z0]), Z * h, X * w, tex, "poster"))
        elif wall == 1:
            x0 = rng.uniform(0.1, W - w - 0.1)
            room.panels.append(Panel(np.array([x0 + w, D - eps, z0]), Z * h, -X * w, tex, "poster"))
        elif wall == 2:
            y0 = rng.uniform(0.1, D - w - 0.1)
            room.panels.append(Panel(np.array([eps, y0 + w, z0]), Z * h, -Y * w, tex, "poster"))
        else:
            y0 = rng.uniform(0.1, D - w - 0.1)
            room.panels.append(Panel(np.array([W - eps, y0, z0]), Z * h, Y * w, tex, "poster"))
    for _ in range(int(rng.integers(2, 5))):
        w, d = rng.uniform(0.8, 2.5), rng.uniform(0.6, 2.0)
        x0, y0 = rng.uniform(0.2, W - w - 0.2), rng.uniform(0.2, D - d - 0.2)
        room.panels.append(Panel(np.array([x0, y0, 0.003]), X * w, Y * d, random_texture(rng, "rug"), "rug"))

    n_lights = int(rng.integers(1, 4))
    room.lights = np.stack([rng.uniform([0.8, 0.8, H - 0.3], [W - 0.8, D - 0.8, H - 0.1]) for _ in range(n_lights)])
    room.light_power = rng.uniform(1.5, 4.0, size=n_lights) / n_lights
    room.ambient = float(rng.uniform(0.2, 0.4))
    room.keepout = boxes
    return room


def _add_front_poster(room: Room, rng: np.random.Generator, lo, hi, wall: int) -> None:
    X, Y, Z = np.eye(3)
    eps = 0.003
    w_avail = (hi - lo)[0] if wall in (0, 1) else (hi - lo)[1]
    h_avail = hi[2] - lo[2]
    w, h = rng.uniform(0.3, 0.9) * w_avail, rng.uniform(0.3, 0.8) * h_avail
    s0, z0 = rng.uniform(0, w_avail - w), lo[2] + rng.uniform(0.05, h_avail - h)
    tex = random_texture(rng, "poster")
    if wall == 0:  # unit at y=0, front at y=hi_y, normal +y
        room.panels.append(Panel(np.array([lo[0] + s0, hi[1] + eps, z0]), Z * h, X * w, tex, "poster"))
    elif wall == 1:  # front at y=lo_y, normal -y
        room.panels.append(Panel(np.array([lo[0] + s0 + w, lo[1] - eps, z0]), Z * h, -X * w, tex, "poster"))
    elif wall == 2:  # front at x=hi_x, normal +x
        room.panels.append(Panel(np.array([hi[0] + eps, lo[1] + s0 + w, z0]), Z * h, -Y * w, tex, "poster"))
    else:  # front at x=lo_x, normal -x
        room.panels.append(Panel(np.array([lo[0] - eps, lo[1] + s0, z0]), Z * h, Y * w, tex, "poster"))
