"""Procedural indoor rooms like 3DMatch's: kitchens, offices, bedrooms, living rooms, conference
rooms and corridors.

A room is a floor plan that is not always a box (L-shapes, alcoves), walls with doorways onto a
corridor and windows with reveals and bars, columns, skirting boards; furniture made of parts
(:mod:`pcrcg.data.synth.furniture`) along the walls and in the room at any yaw, clutter on every
top and on the floor, posters, pictures and printed notices on the walls, rugs on the floor.
Placement uses an occupancy grid of the floor, which also tells the camera where a person can
walk.

Coordinates: metres, z up; the room's bounding box spans [0, W] x [0, D] x [0, H].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcrcg.data.synth import furniture as F
from pcrcg.data.synth.panel import Panel, Room
from pcrcg.data.synth.shapes import box, compose, flat, frustum, placement
from pcrcg.data.synth.textures import Texture, image_texture, material, random_texture

__all__ = ["Panel", "Room", "make_room", "ROOM_TYPES"]

ROOM_TYPES = ("kitchen", "office", "bedroom", "living", "conference", "corridor")
CELL = 0.05  # occupancy grid (m)
# How full a room is (generator v6: rooms as cluttered as 3DMatch's; v5's sparser rooms left the
# low-overlap pairs floor and wall, which geometry cannot register):
WALL_GAP_P = 0.04          # chance of a free stretch of wall at each step along it (v5: 0.1)
INTERIOR_RATE = 2.5        # Poisson mean per unit rate of the interior plan (v5: 1.5)
TOP_CLUTTER = (1.2, 2.4)   # density range of the small things on every top (v5: 0.8-1.8)
FLOOR_CLUTTER = (("carton", 10.0), ("plant", 2.0), ("bin", 1.2), ("chair", 2.0), ("lamp", 0.6))  # v5: 6, 1.5, 0.8, 1, 0
POSTERS_PER_M = 0.7        # posters, pictures and notices per metre of wall (v5: 0.45)


@dataclass
class Wall:
    """A straight wall from ``a`` to ``b`` (2D), the room on its left."""

    a: np.ndarray
    b: np.ndarray

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.b - self.a))

    @property
    def along(self) -> np.ndarray:
        return (self.b - self.a) / self.length

    @property
    def inward(self) -> np.ndarray:
        t = self.along
        return np.array([-t[1], t[0]])

    def frame(self, s: float, off: float = 0.0, z: float = 0.0) -> np.ndarray:
        """Placement at distance ``s`` along the wall, ``off`` into the room: the object's -y (front)
        faces into the room, its +y the wall."""
        p = self.a + self.along * s + self.inward * off
        yaw = np.arctan2(self.along[1], self.along[0])
        return placement(p[0], p[1], z, yaw)


# ------------------------------------------------------------------ floor plans


# (width range, depth range) in metres
_ROOM_SIZES = {"corridor": ((2.2, 3.0), (6.0, 9.0)), "conference": ((5.5, 8.0), (4.5, 7.0)),
               "room": ((4.0, 7.0), (3.6, 6.0))}
_TABLE_SIZES = {"conference": ((2.0, 3.2), (1.0, 1.3)), "coffee": ((0.6, 1.1), (0.45, 0.7)),
                "dining": ((0.9, 1.6), (0.7, 0.95))}


def _uniform_wd(rng: np.random.Generator, ranges) -> tuple[float, float]:
    """A width and a depth drawn uniformly from ``((w_lo, w_hi), (d_lo, d_hi))`` (width first)."""
    (w0, w1), (d0, d1) = ranges
    return rng.uniform(w0, w1), rng.uniform(d0, d1)


def _floor_plan(rng: np.random.Generator, kind: str) -> tuple[list[np.ndarray], list[tuple[float, float, float, float]]]:
    """The plan as a counter-clockwise polygon (V, 2) and the rectangles (x0, y0, x1, y1) that tile it."""
    W, D = _uniform_wd(rng, _ROOM_SIZES.get(kind, _ROOM_SIZES["room"]))
    shape = "box" if kind == "corridor" else str(rng.choice(["box", "L", "alcove"], p=[0.4, 0.35, 0.25]))
    if shape == "L":
        cw, cd = W * rng.uniform(0.3, 0.45), D * rng.uniform(0.3, 0.45)
        poly = [(0, 0), (W, 0), (W, D - cd), (W - cw, D - cd), (W - cw, D), (0, D)]
        rects = [(0, 0, W, D - cd), (0, D - cd, W - cw, D)]
    elif shape == "alcove":
        a0 = rng.uniform(0.5, W - 2.0)
        a1 = a0 + rng.uniform(1.2, min(2.5, W - a0 - 0.3))
        ad = rng.uniform(0.6, 1.2)
        poly = [(0, 0), (W, 0), (W, D), (a1, D), (a1, D + ad), (a0, D + ad), (a0, D), (0, D)]
        rects = [(0, 0, W, D), (a0, D, a1, D + ad)]
    else:
        poly = [(0, 0), (W, 0), (W, D), (0, D)]
        rects = [(0, 0, W, D)]
    return [np.asarray(p, float) for p in poly], rects


class Floor:
    """Occupancy grid of the floor plan: which cells are inside the room and which are taken."""

    def __init__(self, rects, size: np.ndarray):
        self.gx, self.gy = int(np.ceil(size[0] / CELL)) + 1, int(np.ceil(size[1] / CELL)) + 1
        cx = (np.arange(self.gx) + 0.5) * CELL
        cy = (np.arange(self.gy) + 0.5) * CELL
        X, Y = np.meshgrid(cx, cy, indexing="ij")
        self.inside = np.zeros((self.gx, self.gy), bool)
        for x0, y0, x1, y1 in rects:
            self.inside |= (X > x0) & (X < x1) & (Y > y0) & (Y < y1)
        self.taken = np.zeros_like(self.inside)
        self.tall = np.zeros_like(self.inside)  # under things a hand-held camera cannot pass over
        self.X, self.Y = X, Y

    def _cells(self, M: np.ndarray, w: float, d: float, margin: float) -> np.ndarray:
        """Mask of the cells under a w x d footprint at placement M, grown by ``margin``."""
        c, s = M[0, 0], M[1, 0]
        dx, dy = self.X - M[0, 3], self.Y - M[1, 3]
        lu, lv = c * dx + s * dy, -s * dx + c * dy
        return (np.abs(lu) < w / 2 + margin) & (np.abs(lv) < d / 2 + margin)

    def free(self, M: np.ndarray, w: float, d: float, margin: float = 0.03) -> bool:
        m = self._cells(M, w, d, margin)
        inner = self._cells(M, w, d, -0.01)
        return bool(np.all(self.inside[inner]) and not np.any(self.taken[m]) and m.any())

    def take(self, M: np.ndarray, w: float, d: float, h: float = 2.0) -> None:
        m = self._cells(M, w, d, 0.0)
        self.taken |= m
        if h > 1.1:
            self.tall |= m

    def walkable(self, clearance: float) -> np.ndarray:
        """Cells at least ``clearance`` from walls and tall furniture: where a hand-held camera at
        1.2-1.7 m can be (over tables and beds, not through shelves)."""
        from scipy.ndimage import distance_transform_edt

        blocked = ~self.inside | self.tall
        return distance_transform_edt(~blocked) * CELL >= clearance


# ------------------------------------------------------------------ walls, doors, windows


def _wall_panels(room: Room, rng: np.random.Generator, wall: Wall, H: float, tex: Texture, floor: Floor) -> None:
    """A wall with perhaps a doorway or a window, and a skirting board."""
    L = wall.length
    X = np.array([*wall.along, 0.0])
    Z = np.array([0.0, 0.0, 1.0])
    n = np.array([*wall.inward, 0.0])
    a3 = np.array([*wall.a, 0.0])
    openings: list[tuple[float, float, float, float, str]] = []  # s0, s1, z0, z1, kind
    if L > 2.0 and rng.random() < 0.3:
        w = rng.uniform(0.85, 1.0)
        s0 = rng.uniform(0.3, L - w - 0.3)
        openings.append((s0, s0 + w, 0.0, 2.05, "door"))
    if L > 2.2 and rng.random() < 0.4:
        w = rng.uniform(0.9, min(2.0, L - 1.0))
        s0 = rng.uniform(0.4, L - w - 0.4)
        if all(s0 > o[1] + 0.3 or s0 + w < o[0] - 0.3 for o in openings):
            z0 = rng.uniform(0.8, 1.0)
            openings.append((s0, s0 + w, z0, min(H - 0.25, z0 + rng.uniform(1.1, 1.5)), "window"))
    # split the wall into rectangles around the openings (columns of wall between openings)
    cuts = sorted(openings)
    s = 0.0
    for s0, s1, z0, z1, _ in cuts:
        if s0 > s:
            room.panels.append(Panel(a3 + X * s, X * (s0 - s), Z * H, tex, "wall"))
        if z0 > 0:
            room.panels.append(Panel(a3 + X * s0, X * (s1 - s0), Z * z0, tex, "wall"))
        room.panels.append(Panel(a3 + X * s0 + Z * z1, X * (s1 - s0), Z * (H - z1), tex, "wall"))
        s = s1
    if s < L:
        room.panels.append(Panel(a3 + X * s, X * (L - s), Z * H, tex, "wall"))
    frame = material(rng, "paint" if rng.random() < 0.5 else "wood")
    for s0, s1, z0, z1, kind in cuts:
        depth = 0.15 if kind == "window" else 0.12
        o = a3 + X * s0
        B = -n * depth  # reveals go into the wall
        room.panels += [Panel(o + Z * z0, X * (s1 - s0), B, frame, "wall"),  # sill / threshold
                        Panel(o + Z * z1, B, X * (s1 - s0), frame, "wall"),  # head
                        Panel(o + Z * z0, B, Z * (z1 - z0), frame, "wall"),  # jambs
                        Panel(o + X * (s1 - s0) + Z * z0, Z * (z1 - z0), B, frame, "wall")]
        if kind == "window":
            back = o + B
            room.panels.append(Panel(back + Z * z0, X * (s1 - s0), Z * (z1 - z0), _sky(rng), "sky"))
            bar = material(rng, "paint")
            mid = 0.5 * (s0 + s1)
            M = placement(*(np.array([*wall.a, 0]) + X * mid - n * (depth - 0.02))[:2], z0, np.arctan2(X[1], X[0]))
            room.panels += box(M, (0.04, 0.04, z1 - z0), bar, "wall")
            room.panels += box(compose(M, 0, 0, 0.5 * (z1 - z0)), (s1 - s0, 0.04, 0.04), bar, "wall")
        else:  # a short corridor beyond the door: floor, two side walls, back wall, ceiling
            cd = rng.uniform(1.0, 1.8)
            ctex = material(rng, "paint")
            back = o - n * (depth + cd)
            w = s1 - s0
            room.panels += [Panel(o + B, X * w, -n * cd, material(rng, "floor"), "floor"),
                            Panel(back, X * w, Z * z1, ctex, "wall"),
                            Panel(o + B, -n * cd, Z * z1, ctex, "wall"),
                            Panel(o + B + X * w, -n * cd, Z * z1, ctex, "wall"),
                            Panel(o + B + Z * z1, X * w, -n * cd, ctex, "ceiling")]
            # keep the doorway clear of furniture
            M = wall.frame(0.5 * (s0 + s1), 0.5)
            floor.take(M, s1 - s0 + 0.2, 1.0, 0.0)
    # skirting board, broken at doors
    skirt = material(rng, "wood" if rng.random() < 0.5 else "paint")
    s = 0.0
    for s0, s1, z0, _, kind in cuts + [(L, L, 0.0, 0.0, "end")]:
        if kind in ("door", "end") and s0 - s > 0.05:
            M = wall.frame(0.5 * (s + s0), 0.006)
            room.panels += box(M, (s0 - s, 0.012, 0.08), skirt, "wall")
        if kind == "door":
            s = s1


def _sky(rng: np.random.Generator) -> Texture:
    """What a window shows: bright, washed out (no depth: glass)."""
    base = rng.uniform(0.75, 1.0, 3)
    return Texture("noise", np.stack([base, base * 0.9, base * 0.8]), 0.5, 0.0, int(rng.integers(0, 2**31 - 1)), 0.02)


# ------------------------------------------------------------------ furniture placement

_WALL_ITEMS = {
    "kitchen": (["counter", "fridge", "shelf", "cabinet"], [0.55, 0.15, 0.15, 0.15]),
    "office": (["desk", "shelf", "cabinet", "sofa"], [0.45, 0.3, 0.2, 0.05]),
    "bedroom": (["bed", "shelf", "cabinet", "desk"], [0.35, 0.25, 0.25, 0.15]),
    "living": (["sofa", "shelf", "cabinet", "desk"], [0.4, 0.3, 0.25, 0.05]),
    "conference": (["cabinet", "shelf", "desk"], [0.4, 0.4, 0.2]),
    "corridor": (["cabinet", "shelf"], [0.5, 0.5]),
}


def _wall_item(rng, kind: str, M: np.ndarray) -> F.Item:
    if kind == "counter":
        return F.cabinet(rng, M, w=rng.uniform(0.8, 2.4), h=0.87, counter=True)
    return {"fridge": F.fridge, "shelf": F.bookshelf, "cabinet": F.cabinet, "desk": F.desk, "sofa": F.sofa,
            "bed": F.bed}[kind](rng, M)


def _place_along_walls(room: Room, rng, walls: list[Wall], floor: Floor, rtype: str, H: float, tops: list) -> None:
    names, p = _WALL_ITEMS[rtype]
    for wall in walls:
        s = rng.uniform(0.05, 0.6)
        while s < wall.length - 0.4:
            if rng.random() < WALL_GAP_P:
                s += rng.uniform(0.3, 1.0)
                continue
            kind = str(rng.choice(names, p=p))
            # build at the origin first to know the size, then place
            probe = _wall_item(np.random.default_rng(int(rng.integers(0, 2**31))), kind, np.eye(4))
            w, d = probe.size[0], probe.size[1]
            if s + w > wall.length - 0.02:
                break
            jitter = rng.normal(0, 0.03)
            M = wall.frame(s + w / 2, d / 2 + 0.01 + abs(rng.normal(0, 0.01)))
            M = M @ placement(0, 0, 0, np.pi + jitter)  # front into the room
            if floor.free(M, w, d, 0.02):
                item = _wall_item(rng, kind, M)
                room.panels += item.panels
                floor.take(M, w, d, item.size[2])
                tops += item.tops
                if kind == "counter" and rng.random() < 0.7 and H > 2.3:  # upper cabinets above
                    Mu = wall.frame(s + w / 2, 0.17, 1.45) @ placement(0, 0, 0, np.pi)
                    room.panels += F.wall_cabinet(rng, Mu, w).panels
                if kind == "desk" and rng.random() < 0.8:  # its chair
                    Mc = M @ placement(rng.normal(0, 0.15), -d / 2 - 0.15, 0, np.pi + rng.normal(0, 0.5))
                    if floor.free(Mc, 0.5, 0.5, 0.0):
                        room.panels += F.chair(rng, Mc).panels
                        floor.take(Mc, 0.5, 0.5, 0.9)
                s += w + rng.uniform(0.0, 0.15)
            else:
                s += 0.15


def _random_spot(rng, floor: Floor, w: float, d: float, margin: float, tries: int = 30) -> np.ndarray | None:
    ix, iy = np.nonzero(floor.inside & ~floor.taken)
    if len(ix) == 0:
        return None
    for _ in range(tries):
        k = int(rng.integers(0, len(ix)))
        M = placement((ix[k] + 0.5) * CELL, (iy[k] + 0.5) * CELL, 0, rng.uniform(0, 2 * np.pi))
        if floor.free(M, w, d, margin):
            return M
    return None


def _place_interior(room: Room, rng, floor: Floor, rtype: str, tops: list) -> None:
    plan = {
        "kitchen": [("dining", 0.8), ("plant", 0.5), ("bin", 0.8), ("carton", 1.0)],
        "office": [("dining", 0.4), ("chair", 1.0), ("plant", 0.8), ("bin", 1.0), ("carton", 1.5)],
        "bedroom": [("chair", 0.5), ("lamp", 0.6), ("plant", 0.5), ("carton", 1.5), ("bin", 0.5)],
        "living": [("coffee", 1.0), ("armchair", 0.8), ("lamp", 0.7), ("plant", 1.0), ("carton", 1.0)],
        "conference": [("conference", 1.0), ("plant", 0.6), ("bin", 0.5), ("carton", 0.6)],
        "corridor": [("plant", 0.5), ("bin", 0.5), ("carton", 1.0)],
    }[rtype]
    for what, rate in plan:
        for _ in range(int(rng.poisson(INTERIOR_RATE * rate))):
            _place_one(room, rng, floor, what, tops)


def _place_one(room: Room, rng, floor: Floor, what: str, tops: list) -> None:
    if what in ("dining", "conference", "coffee"):
        w, d = _uniform_wd(rng, _TABLE_SIZES[what])
        M = _random_spot(rng, floor, w + 1.0, d + 1.0, 0.1)
        if M is None:
            return
        it = F.table(rng, M, w, d)
        if what == "coffee":  # a low table: squash it
            S = np.diag([1.0, 1.0, 0.55, 1.0])
            it = F.table(rng, M @ S, w, d)
            it.tops = [F.Surface(M @ placement(0, 0, 0.42), w, d)]
        room.panels += it.panels
        floor.take(M, w, d, 0.8)
        tops += it.tops
        if room.focus is None:
            room.focus = M[:2, 3].copy()
        if what != "coffee":  # chairs around it, pushed out and turned
            n_side = max(1, int(w / 0.6))
            for side in (-1, 1):
                for k in range(n_side):
                    if rng.random() < 0.25:
                        continue
                    x = -w / 2 + w / n_side * (k + 0.5)
                    Mc = M @ placement(x + rng.normal(0, 0.05), side * (d / 2 + rng.uniform(0.1, 0.35)), 0,
                                       (0 if side > 0 else np.pi) + rng.normal(0, 0.35))
                    if floor.free(Mc, 0.48, 0.48, 0.0):
                        room.panels += F.chair(rng, Mc).panels
                        floor.take(Mc, 0.48, 0.48, 0.9)
        return
    make = {"chair": F.chair, "armchair": F.sofa, "lamp": F.lamp, "plant": F.plant, "bin": F.bin_, "carton": F.carton}[what]
    probe = make(np.random.default_rng(int(rng.integers(0, 2**31))), np.eye(4))
    w, d = probe.size[:2]
    if what == "armchair":
        w, d = 1.0, 0.95
    M = _random_spot(rng, floor, w, d, 0.05)
    if M is None:
        return
    it = make(rng, M)
    room.panels += it.panels
    floor.take(M, it.size[0], it.size[1], it.size[2])


# ------------------------------------------------------------------ wall decoration


def _decorate_walls(room: Room, rng, walls: list[Wall], H: float) -> None:
    """Posters, pictures, notices and a whiteboard, a few millimetres off the wall."""
    for wall in walls:
        for _ in range(int(rng.poisson(POSTERS_PER_M * wall.length))):
            w, h = rng.uniform(0.25, 1.2), rng.uniform(0.25, 0.9)
            if w > wall.length - 0.2:
                continue
            s = rng.uniform(0.1 + w / 2, wall.length - 0.1 - w / 2)
            z = rng.uniform(1.0, max(1.05, H - h - 0.3))
            M = wall.frame(s, 0.004 + 0.01 * (rng.random() < 0.4), z)
            kind = rng.random()
            if kind < 0.65:
                tex = image_texture(rng, (w, h))
            elif kind < 0.8:  # a whiteboard
                tex = material(rng, "plastic")
                tex.colors = np.clip(tex.colors * 0.1 + 0.88, 0, 1)
            else:
                tex = random_texture(rng, "poster")
            room.panels.append(flat(M, w, h, tex, "poster"))
            if rng.random() < 0.4:  # a frame around it
                fr = material(rng, "wood")
                for dz, ww, hh in ((0, w + 0.04, 0.02), (h, w + 0.04, 0.02)):
                    room.panels += box(compose(M, 0, 0.01, dz - 0.01), (ww, 0.02, hh), fr, "poster")
                for dx in (-w / 2, w / 2):
                    room.panels += box(compose(M, dx, 0.01, 0), (0.02, 0.02, h), fr, "poster")


# ------------------------------------------------------------------ the room


def make_room(rng: np.random.Generator, room_type: str | None = None) -> Room:
    """A random furnished room of ``room_type`` (one of :data:`ROOM_TYPES`; random when None).

    Steps, in the order they draw from ``rng``: the type, floor plan and height; the shell (floor,
    ceiling and walls with their openings: :func:`_shell`); columns (:func:`_columns`); furniture along
    the walls and in the room, with clutter on its tops (:func:`_furnish`); clutter and rugs on the floor
    (:func:`_floor_clutter`); things on the walls (:func:`_decorate_walls`); the lights (:func:`_light`)."""
    rtype = room_type or str(rng.choice(ROOM_TYPES, p=[0.22, 0.24, 0.16, 0.18, 0.1, 0.1]))
    poly, rects = _floor_plan(rng, rtype)
    W = max(p[0] for p in poly)
    D = max(p[1] for p in poly)
    H = rng.uniform(2.5, 3.0)
    room = Room(size=np.array([W, D, H]))
    floor = Floor(rects, room.size)
    walls = _shell(room, rng, poly, rects, H, floor)
    _columns(room, rng, floor, H)
    tops = _furnish(room, rng, walls, floor, rtype, H)
    _floor_clutter(room, rng, floor, tops)
    _decorate_walls(room, rng, walls, H)
    _light(room, rng, floor, H)
    room.cell = CELL
    room.walkable = floor.walkable(0.55)
    room.room_type = rtype
    return room


def _shell(room: Room, rng: np.random.Generator, poly: list[np.ndarray], rects: list[tuple[float, float, float, float]],
           H: float, floor: Floor) -> list[Wall]:
    """Floor and ceiling over the plan's rectangles, and the walls along its outline (one wall in four,
    at random, in an accent material); the walls."""
    X, Y, Z = np.eye(3)
    ftex, ctex = material(rng, "floor"), material(rng, "paint")
    for x0, y0, x1, y1 in rects:
        room.panels.append(Panel(np.array([x0, y0, 0]), X * (x1 - x0), Y * (y1 - y0), ftex, "floor"))
        room.panels.append(Panel(np.array([x0, y1, H]), X * (x1 - x0), -Y * (y1 - y0), ctex, "ceiling"))
    walls = [Wall(poly[k], poly[(k + 1) % len(poly)]) for k in range(len(poly))]
    main_tex = material(rng, "wall")
    accent = material(rng, "wall")
    for wall in walls:
        _wall_panels(room, rng, wall, H, accent if rng.random() < 0.25 else main_tex, floor)
    return walls


def _columns(room: Room, rng: np.random.Generator, floor: Floor, H: float) -> None:
    """Columns, square or round, free-standing or by a wall (a Poisson number, 0.6 on average)."""
    for _ in range(int(rng.poisson(0.6))):
        r = rng.uniform(0.12, 0.3)
        M = _random_spot(rng, floor, 2 * r, 2 * r, 0.05)
        if M is not None:
            tex = material(rng, "paint")
            room.panels += frustum(M, r, r, H, int(rng.choice([4, 16, 24])), tex, "wall", top=False)
            floor.take(M, 2 * r, 2 * r, H)


def _furnish(room: Room, rng: np.random.Generator, walls: list[Wall], floor: Floor, rtype: str, H: float) -> list:
    """Furniture along the walls and in the room, then clutter on the tops below 1.6 m; the tops
    (:class:`pcrcg.data.synth.furniture.Surface`), where floor clutter may also land."""
    tops: list[F.Surface] = []
    _place_along_walls(room, rng, walls, floor, rtype, H, tops)
    _place_interior(room, rng, floor, rtype, tops)
    for top in tops:
        if top.M[2, 3] < 1.6:
            room.panels += F.clutter_on(rng, top, density=rng.uniform(*TOP_CLUTTER))
    return tops


def _floor_clutter(room: Room, rng: np.random.Generator, floor: Floor, tops: list) -> None:
    """Things on the floor (:data:`FLOOR_CLUTTER`, Poisson numbers) and rugs."""
    for what, rate in FLOOR_CLUTTER:
        for _ in range(int(rng.poisson(rate))):
            _place_one(room, rng, floor, what, tops)
    for _ in range(int(rng.poisson(0.8))):
        w, d = rng.uniform(0.8, 2.2), rng.uniform(0.6, 1.6)
        M = _random_spot(rng, floor, 0.3, 0.3, 0.0)
        if M is not None:
            tex = random_texture(rng, "rug") if rng.random() < 0.5 else material(rng, "fabric")
            room.panels += box(M @ placement(0, 0, 0.0), (w, d, 0.006), tex, "rug")


def _light(room: Room, rng: np.random.Generator, floor: Floor, H: float) -> None:
    """One to three point lights 10-30 cm under the ceiling over the floor, their power shared, and the
    ambient light."""
    n_lights = int(rng.integers(1, 4))
    lights = []
    for _ in range(n_lights):
        ix, iy = np.nonzero(floor.inside)
        k = int(rng.integers(0, len(ix)))
        lights.append([(ix[k] + 0.5) * CELL, (iy[k] + 0.5) * CELL, H - rng.uniform(0.1, 0.3)])
    room.lights = np.asarray(lights)
    room.light_power = rng.uniform(1.5, 4.0, size=n_lights) / n_lights
    room.ambient = float(rng.uniform(0.08, 0.2))
