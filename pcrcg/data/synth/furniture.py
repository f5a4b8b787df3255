"""Furniture made of parts, and the small things that clutter real rooms.

Each builder takes the random generator and a placement ``M`` (object-to-room, the object stands
on z = 0 of its frame, centred on x = y = 0, its front facing -y) and returns an :class:`Item`:
its panels, its footprint and the tops that can hold clutter. Sizes are those of real furniture
(metres).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from pcrcg.data.synth.panel import Panel
from pcrcg.data.synth.shapes import box, compose, ellipsoid, flat, frustum, leaves
from pcrcg.data.synth.textures import Texture, image_texture, material, random_palette


@dataclass
class Surface:
    """A horizontal top (w x d at height z of the item's frame ``M``) that can hold clutter."""

    M: np.ndarray
    w: float
    d: float


@dataclass
class Item:
    panels: list[Panel]
    size: tuple[float, float, float]  # footprint w, d and height (item frame)
    tops: list[Surface] = field(default_factory=list)


def _tex(rng: np.random.Generator, kinds: tuple[str, ...], p=None) -> Texture:
    return material(rng, str(rng.choice(kinds, p=p)))


def _colored(rng: np.random.Generator, lo: float = 0.1, hi: float = 0.9) -> Texture:
    pal = random_palette(rng, 0.08)
    pal[0] = rng.uniform(lo, hi, 3)
    return Texture("noise", pal, 0.1, 0.0, int(rng.integers(0, 2**31 - 1)), 0.03)


# ------------------------------------------------------------------ seating and tables


def chair(rng: np.random.Generator, M: np.ndarray) -> Item:
    """A chair: four legs, a seat, a back (an office chair: a star base, a column)."""
    tex = _tex(rng, ("wood", "plastic", "metal"))
    seat_tex = _tex(rng, ("fabric", "wood", "plastic"))
    w, d, hs = rng.uniform(0.4, 0.5), rng.uniform(0.4, 0.5), rng.uniform(0.42, 0.48)
    P: list[Panel] = []
    if rng.random() < 0.35:  # office chair
        for k in range(5):
            a = 2 * np.pi * k / 5
            P += box(compose(M, 0.15 * np.cos(a), 0.15 * np.sin(a), 0.03, yaw=a), (0.3, 0.04, 0.04), tex, "furniture")
        P += frustum(compose(M, 0, 0, 0.07), 0.025, 0.025, hs - 0.12, 8, tex, "furniture")
        P += box(compose(M, 0, 0, hs - 0.07), (w, d, 0.07), seat_tex, "furniture", bottom=True)
        P += box(compose(M, 0, d / 2 - 0.03, hs + 0.1, pitch=0.0, roll=-0.12), (w * 0.95, 0.06, rng.uniform(0.4, 0.55)),
                 seat_tex, "furniture", bottom=True)
    else:
        leg = rng.uniform(0.025, 0.04)
        for sx in (-1, 1):
            for sy in (-1, 1):
                P += box(compose(M, sx * (w / 2 - leg), sy * (d / 2 - leg), 0), (leg, leg, hs - 0.03), tex, "furniture")
        P += box(compose(M, 0, 0, hs - 0.03), (w, d, 0.03), seat_tex, "furniture", bottom=True)
        hb = rng.uniform(0.35, 0.5)
        for sx in (-1, 1):
            P += box(compose(M, sx * (w / 2 - leg), d / 2 - leg, hs), (leg, leg, hb), tex, "furniture")
        P += box(compose(M, 0, d / 2 - leg, hs + hb * rng.uniform(0.4, 0.7), roll=-0.08), (w, 0.025, hb * 0.35), tex,
                 "furniture", bottom=True)
    return Item(P, (w, d, hs + 0.5))


def table(rng: np.random.Generator, M: np.ndarray, w: float | None = None, d: float | None = None) -> Item:
    """A table: a top on four legs, a trestle or one column (round tables)."""
    tex = _tex(rng, ("wood", "wood", "plastic", "metal"))
    h = rng.uniform(0.72, 0.77)
    t = rng.uniform(0.025, 0.045)
    P: list[Panel] = []
    if w is None and rng.random() < 0.25:  # round
        r = rng.uniform(0.4, 0.6)
        P += frustum(compose(M, 0, 0, h - t), r, r, t, 24, tex, "furniture", bottom=True)
        P += frustum(compose(M, 0, 0, 0.02), 0.04, 0.04, h - t - 0.02, 10, tex, "furniture")
        P += frustum(M, 0.28, 0.26, 0.02, 16, tex, "furniture")
        return Item(P, (2 * r, 2 * r, h), [Surface(compose(M, 0, 0, h), 1.3 * r, 1.3 * r)])
    w = w or rng.uniform(0.8, 1.8)
    d = d or rng.uniform(0.6, 1.0)
    P += box(compose(M, 0, 0, h - t), (w, d, t), tex, "furniture", bottom=True)
    leg_tex = tex if rng.random() < 0.6 else _tex(rng, ("metal",))
    leg = rng.uniform(0.04, 0.07)
    round_legs = rng.random() < 0.4
    for sx in (-1, 1):
        for sy in (-1, 1):
            Ml = compose(M, sx * (w / 2 - leg - 0.03), sy * (d / 2 - leg - 0.03), 0)
            P += frustum(Ml, leg / 2, leg / 2, h - t, 8, leg_tex, "furniture") if round_legs else \
                box(Ml, (leg, leg, h - t), leg_tex, "furniture")
    if rng.random() < 0.5:  # an apron under the top
        P += box(compose(M, 0, -d / 2 + 0.05, h - t - 0.08), (w - 0.1, 0.02, 0.08), tex, "furniture")
    return Item(P, (w, d, h), [Surface(compose(M, 0, 0, h), w, d)])


def desk(rng: np.random.Generator, M: np.ndarray) -> Item:
    """A desk against a wall: a table with a drawer unit, a monitor, a keyboard."""
    w, d = rng.uniform(1.0, 1.6), rng.uniform(0.6, 0.8)
    it = table(rng, M, w, d)
    h = it.size[2]
    tex = _tex(rng, ("wood", "plastic"))
    side = rng.choice([-1, 1])
    it.panels += box(compose(M, side * (w / 2 - 0.25), 0, 0), (0.4, d - 0.1, h - 0.06), tex, "furniture")
    for k in range(3):  # drawer fronts and handles
        z = 0.06 + k * (h - 0.12) / 3
        it.panels += box(compose(M, side * (w / 2 - 0.25), -d / 2 + 0.04, z), (0.38, 0.01, (h - 0.12) / 3 - 0.01), tex, "furniture")
        it.panels += box(compose(M, side * (w / 2 - 0.25), -d / 2 + 0.03, z + 0.12), (0.1, 0.015, 0.015), material(rng, "metal"), "furniture")
    if rng.random() < 0.85:  # monitor: base, neck, screen
        mx = rng.uniform(-w / 4, w / 4)
        dark = material(rng, "plastic")
        dark.colors = dark.colors * 0.25
        Mm = compose(M, mx, d / 2 - 0.2, h, yaw=rng.uniform(-0.3, 0.3))
        it.panels += box(Mm, (0.22, 0.18, 0.015), dark, "furniture")
        it.panels += box(compose(Mm, 0, 0.03, 0.015), (0.05, 0.03, 0.12), dark, "furniture")
        sw, sh = rng.uniform(0.5, 0.62), rng.uniform(0.3, 0.38)
        it.panels += box(compose(Mm, 0, 0, 0.1), (sw, 0.03, sh), dark, "furniture")
        if rng.random() < 0.6:  # something on the screen
            it.panels.append(flat(compose(Mm, 0, -0.016, 0.12), sw - 0.04, sh - 0.04,
                                  image_texture(rng, (sw - 0.04, sh - 0.04)), "screen"))
    it.panels += box(compose(M, rng.uniform(-0.2, 0.2), -d / 2 + 0.2, h, yaw=rng.normal(0, 0.1)), (0.44, 0.14, 0.02),
                     material(rng, "plastic"), "furniture")
    it.size = (w, d, h + 0.55)  # with the monitor
    return it


def sofa(rng: np.random.Generator, M: np.ndarray) -> Item:
    """A sofa or armchair: base, back, arms and cushions."""
    tex = material(rng, "fabric")
    seats = int(rng.choice([1, 2, 3]))
    sw = rng.uniform(0.55, 0.7)
    w, d = seats * sw + 0.3, rng.uniform(0.8, 0.95)
    P = box(compose(M, 0, 0, 0.08), (w, d, 0.3), tex, "furniture")
    for sx in (-1, 1):
        P += box(compose(M, sx * (w / 2 - 0.08), 0, 0.08), (0.16, d, rng.uniform(0.55, 0.65)), tex, "furniture")
    P += box(compose(M, 0, d / 2 - 0.1, 0.08), (w, 0.2, rng.uniform(0.75, 0.9)), tex, "furniture")
    leg = material(rng, "wood")
    for sx in (-1, 1):
        for sy in (-1, 1):
            P += frustum(compose(M, sx * (w / 2 - 0.06), sy * (d / 2 - 0.06), 0), 0.025, 0.02, 0.08, 6, leg, "furniture")
    for k in range(seats):  # seat cushions: rounded tops
        cx = -w / 2 + 0.15 + sw * (k + 0.5)
        P += ellipsoid(compose(M, cx, -0.05, 0.38), (sw * 0.48, d * 0.38, 0.08), 3, 12, tex, "furniture", z_min=0.0)
    for _ in range(int(rng.integers(0, 3))):  # throw pillows, leaning
        px = rng.uniform(-w / 2 + 0.3, w / 2 - 0.3)
        P += ellipsoid(compose(M, px, d / 2 - 0.28, 0.6, roll=0.4, yaw=rng.normal(0, 0.3)), (0.2, 0.07, 0.2), 4, 10,
                       _tex(rng, ("fabric",)), "furniture")
    return Item(P, (w, d, 0.9))


def bed(rng: np.random.Generator, M: np.ndarray) -> Item:
    """A bed: frame, mattress, duvet, pillows, headboard."""
    w, L = rng.choice([0.9, 1.4, 1.6]) + 0.1, rng.uniform(2.0, 2.15)
    frame = material(rng, "wood")
    P = box(compose(M, 0, 0, 0), (w, L, 0.3), frame, "furniture")
    P += box(compose(M, 0, 0, 0.3), (w - 0.06, L - 0.06, 0.18), material(rng, "fabric"), "furniture")
    duvet = material(rng, "fabric")
    P += box(compose(M, 0, -0.2, 0.44, roll=0.01), (w + 0.04, L * 0.7, 0.1), duvet, "furniture")
    P += box(compose(M, 0, L / 2 - 0.03, 0), (w, 0.05, rng.uniform(0.9, 1.2)), frame, "furniture")
    for k in range(1 if w < 1.2 else 2):
        px = 0 if w < 1.2 else (k - 0.5) * w / 2
        P += ellipsoid(compose(M, px, L / 2 - 0.3, 0.52), (0.3, 0.18, 0.07), 3, 10, material(rng, "fabric"), "furniture")
    return Item(P, (w, L, 1.0))


# ------------------------------------------------------------------ storage


def _books(rng: np.random.Generator, M: np.ndarray, width: float, depth: float, max_h: float) -> list[Panel]:
    """A row of books standing on a board (some leaning), from x = -width/2."""
    P: list[Panel] = []
    x = -width / 2 + rng.uniform(0, 0.1)
    while x < width / 2 - 0.05:
        if rng.random() < 0.15:
            x += rng.uniform(0.05, 0.25)
            continue
        t = rng.uniform(0.015, 0.06)
        h = min(max_h - 0.01, rng.uniform(0.15, 0.3))
        dd = min(depth - 0.02, rng.uniform(0.12, 0.24))
        lean = rng.uniform(-0.25, 0.0) if rng.random() < 0.1 else 0.0
        P += box(compose(M, x + t / 2, -depth / 2 + dd / 2 + 0.01, 0, pitch=lean), (t, dd, h), _colored(rng), "furniture")
        x += t + 0.002
    return P


def bookshelf(rng: np.random.Generator, M: np.ndarray) -> Item:
    """An open shelf unit: sides, boards, back, books and boxes."""
    tex = _tex(rng, ("wood", "wood", "plastic"))
    w, d, h = rng.uniform(0.6, 1.2), rng.uniform(0.28, 0.4), rng.uniform(0.8, 2.0)
    th = 0.02
    P: list[Panel] = []
    for sx in (-1, 1):
        P += box(compose(M, sx * (w / 2 - th / 2), 0, 0), (th, d, h), tex, "furniture")
    P += box(compose(M, 0, d / 2 - 0.005, 0), (w, 0.01, h), tex, "furniture")
    n = max(2, int(h / 0.35))
    tops = []
    for k in range(n + 1):
        z = k * (h - th) / n
        P += box(compose(M, 0, 0, z), (w - 2 * th, d, th), tex, "furniture", bottom=k == 0)
        if k < n:
            gap = (h - th) / n - th
            if rng.random() < 0.75:
                P += _books(rng, compose(M, 0, 0, z + th), w - 2 * th - 0.02, d, gap)
            elif rng.random() < 0.6:
                P += box(compose(M, rng.uniform(-w / 4, w / 4), -0.02, z + th, yaw=rng.normal(0, 0.2)),
                         (rng.uniform(0.15, 0.3), d * 0.8, gap * rng.uniform(0.4, 0.9)), _colored(rng), "furniture")
    tops.append(Surface(compose(M, 0, 0, h), w, d))
    return Item(P, (w, d, h), tops)


def cabinet(rng: np.random.Generator, M: np.ndarray, w: float | None = None, h: float | None = None,
            counter: bool = False) -> Item:
    """A cabinet or a kitchen base unit: body, doors with gaps, handles, an optional counter top."""
    tex = _tex(rng, ("wood", "plastic", "paint"))
    w = w or rng.uniform(0.5, 1.2)
    h = h or rng.uniform(0.7, 1.1)
    d = rng.uniform(0.4, 0.6)
    P = box(compose(M, 0, 0, 0.08), (w, d, h - 0.08), tex, "furniture")
    P += box(compose(M, 0, -0.03, 0), (w - 0.02, d - 0.06, 0.08), _tex(rng, ("plastic",)), "furniture")  # plinth
    n_doors = max(1, int(round(w / 0.45)))
    dw = w / n_doors
    handle = material(rng, "metal")
    drawer = rng.random() < 0.5
    for k in range(n_doors):
        cx = -w / 2 + dw * (k + 0.5)
        dh = h - 0.12 - (0.18 if drawer else 0)
        P += box(compose(M, cx, -d / 2 - 0.009, 0.1), (dw - 0.006, 0.018, dh), tex, "furniture")
        hx = cx + (dw / 2 - 0.06) * (1 if k % 2 else -1)
        P += box(compose(M, hx, -d / 2 - 0.03, 0.1 + dh * 0.7), (0.015, 0.02, 0.12), handle, "furniture")
        if drawer:
            P += box(compose(M, cx, -d / 2 - 0.009, h - 0.19), (dw - 0.006, 0.018, 0.16), tex, "furniture")
            P += box(compose(M, cx, -d / 2 - 0.03, h - 0.12), (0.12, 0.02, 0.015), handle, "furniture")
    top_h = h
    if counter:
        ct = _tex(rng, ("tiles", "wood", "metal"))
        P += box(compose(M, 0, -0.02, h), (w + 0.01, d + 0.04, 0.03), ct, "furniture", bottom=True)
        top_h = h + 0.03
    return Item(P, (w, d, top_h), [Surface(compose(M, 0, -0.02, top_h), w, d)])


def wall_cabinet(rng: np.random.Generator, M: np.ndarray, w: float) -> Item:
    """An upper kitchen cabinet hung on the wall (M at the wall, z = its bottom)."""
    tex = _tex(rng, ("wood", "plastic", "paint"))
    d, h = rng.uniform(0.3, 0.36), rng.uniform(0.6, 0.8)
    P = box(M, (w, d, h), tex, "furniture", bottom=True)
    n = max(1, int(round(w / 0.45)))
    for k in range(n):
        cx = -w / 2 + w / n * (k + 0.5)
        P += box(compose(M, cx, -d / 2 - 0.009, 0.01), (w / n - 0.006, 0.018, h - 0.02), tex, "furniture")
        P += box(compose(M, cx + (w / n / 2 - 0.05) * (1 if k % 2 else -1), -d / 2 - 0.03, 0.05), (0.015, 0.02, 0.1),
                 material(rng, "metal"), "furniture")
    return Item(P, (w, d, h))


def fridge(rng: np.random.Generator, M: np.ndarray) -> Item:
    tex = material(rng, "metal")
    w, d, h = rng.uniform(0.6, 0.75), 0.65, rng.uniform(1.6, 1.9)
    P = box(M, (w, d, h), tex, "furniture")
    split = h * rng.uniform(0.55, 0.7)
    P += box(compose(M, 0, -d / 2 - 0.01, 0.05), (w - 0.01, 0.02, split - 0.06), tex, "furniture")
    P += box(compose(M, 0, -d / 2 - 0.01, split), (w - 0.01, 0.02, h - split - 0.02), tex, "furniture")
    hx = w / 2 - 0.07
    P += box(compose(M, hx, -d / 2 - 0.04, split - 0.45), (0.025, 0.03, 0.35), material(rng, "plastic"), "furniture")
    P += box(compose(M, hx, -d / 2 - 0.04, split + 0.05), (0.025, 0.03, 0.25), material(rng, "plastic"), "furniture")
    return Item(P, (w, d, h), [Surface(compose(M, 0, 0, h), w, d)])


# ------------------------------------------------------------------ smaller things


def lamp(rng: np.random.Generator, M: np.ndarray, floor: bool = True) -> Item:
    tex = _tex(rng, ("metal", "plastic"))
    shade = _tex(rng, ("fabric", "paint"))
    s = 1.0 if floor else rng.uniform(0.3, 0.4)
    h = rng.uniform(1.4, 1.7) * s
    P = frustum(M, 0.15 * s + 0.03, 0.13 * s + 0.02, 0.03, 16, tex, "furniture")
    P += frustum(compose(M, 0, 0, 0.03), 0.015, 0.015, h - 0.03, 8, tex, "furniture")
    r = rng.uniform(0.15, 0.22) * (1 if floor else 0.8)
    P += frustum(compose(M, 0, 0, h - 0.05), r, r * rng.uniform(0.55, 0.8), rng.uniform(0.2, 0.28) * (1 if floor else 0.7),
                 16, shade, "furniture", top=False)
    return Item(P, (2 * r, 2 * r, h + 0.2))


def plant(rng: np.random.Generator, M: np.ndarray, scale: float = 1.0) -> Item:
    """A pot with soil and a crown of leaves."""
    pot = _tex(rng, ("paint", "plastic"))
    r = rng.uniform(0.1, 0.2) * scale
    hp = rng.uniform(0.15, 0.35) * scale
    P = frustum(M, r * 0.75, r, hp, 14, pot, "furniture", top=False)
    P += frustum(compose(M, 0, 0, hp - 0.03), r * 0.95, r * 0.95, 0.0, 14, material(rng, "fabric"), "furniture")
    green = Texture("noise", np.clip(np.array([[0.15, 0.35, 0.1], [0.3, 0.5, 0.15], [0.1, 0.25, 0.08]])
                                     * rng.uniform(0.7, 1.3), 0, 1), 0.05, 0.0, int(rng.integers(0, 2**31 - 1)), 0.1)
    crown = rng.uniform(0.2, 0.5) * scale
    n = int(rng.integers(40, 120) * scale)
    P += frustum(compose(M, 0, 0, hp), 0.01, 0.008, crown * 0.8, 5, green, "plant", top=False)
    P += leaves(M, rng, n, crown, hp + crown * 0.8, rng.uniform(0.08, 0.18) * scale, green)
    return Item(P, (2 * max(r, crown * 0.8), 2 * max(r, crown * 0.8), hp + 2 * crown))


def bin_(rng: np.random.Generator, M: np.ndarray) -> Item:
    r, h = rng.uniform(0.12, 0.2), rng.uniform(0.3, 0.5)
    tex = _tex(rng, ("plastic", "metal"))
    P = frustum(M, r * 0.85, r, h, 16, tex, "furniture", top=False)
    return Item(P, (2 * r, 2 * r, h))


def carton(rng: np.random.Generator, M: np.ndarray, small: bool = False) -> Item:
    """A box: cardboard, a storage crate or a printed package, sometimes two stacked."""
    s = rng.uniform(0.08, 0.25, 3) if small else rng.uniform(0.25, 0.6, 3)
    tex = image_texture(rng, (s[0], s[2])) if rng.random() < 0.3 else _colored(rng, 0.3, 0.8)
    P = box(M, s, tex, "furniture")
    if not small and rng.random() < 0.35:
        s2 = s * rng.uniform(0.5, 0.9, 3)
        P += box(compose(M, 0, 0, s[2], yaw=rng.uniform(-0.6, 0.6)), s2, _colored(rng, 0.3, 0.8), "furniture")
    return Item(P, (s[0], s[1], s[2]))


def bottle(rng: np.random.Generator, M: np.ndarray) -> Item:
    r, h = rng.uniform(0.03, 0.05), rng.uniform(0.18, 0.32)
    tex = _colored(rng)
    P = frustum(M, r, r, h * 0.65, 10, tex, "furniture", top=False)
    P += frustum(compose(M, 0, 0, h * 0.65), r, 0.013, h * 0.2, 10, tex, "furniture", top=False)
    P += frustum(compose(M, 0, 0, h * 0.85), 0.013, 0.013, h * 0.15, 8, tex, "furniture")
    return Item(P, (2 * r, 2 * r, h))


def mug(rng: np.random.Generator, M: np.ndarray) -> Item:
    r, h = rng.uniform(0.035, 0.045), rng.uniform(0.08, 0.11)
    tex = _colored(rng)
    P = frustum(M, r, r, h, 12, tex, "furniture", top=False)
    P += box(compose(M, r + 0.012, 0, h * 0.25), (0.02, 0.012, h * 0.55), tex, "furniture")
    return Item(P, (2 * r + 0.03, 2 * r, h))


def bowl(rng: np.random.Generator, M: np.ndarray) -> Item:
    r = rng.uniform(0.07, 0.14)
    P = ellipsoid(compose(M, 0, 0, r * 0.5), (r, r, r * 0.5), 3, 14, _colored(rng), "furniture", z_min=-1.0)
    return Item(P[: len(P) // 2 + 14], (2 * r, 2 * r, r * 0.5))


def papers(rng: np.random.Generator, M: np.ndarray) -> Item:
    """A few sheets or a magazine lying flat, slightly turned."""
    P = []
    w, d = rng.uniform(0.2, 0.3), rng.uniform(0.28, 0.32)
    for k in range(int(rng.integers(1, 4))):
        Mk = compose(M, *rng.normal(0, 0.02, 2), 0.002 + 0.002 * k, yaw=rng.normal(0, 0.3))
        P += box(Mk, (w, d, 0.002), image_texture(rng, (w, d)), "furniture", top=True)
    return Item(P, (w, d, 0.01))


CLUTTER: tuple[Callable[[np.random.Generator, np.ndarray], Item], ...] = (
    bottle, mug, bowl, papers, lambda rng, M: carton(rng, M, small=True), lambda rng, M: plant(rng, M, 0.45),
    lambda rng, M: lamp(rng, M, floor=False),
)
CLUTTER_P = np.array([0.2, 0.2, 0.1, 0.15, 0.2, 0.1, 0.05])


def clutter_on(rng: np.random.Generator, top: Surface, density: float = 1.0) -> list[Panel]:
    """Small things scattered on a top (turned any way), none hanging over its edge."""
    P: list[Panel] = []
    n = rng.poisson(density * max(0.5, top.w * top.d * 6))
    placed: list[tuple[float, float, float]] = []
    for _ in range(int(n)):
        make = CLUTTER[int(rng.choice(len(CLUTTER), p=CLUTTER_P))]
        for _try in range(6):
            x, y = rng.uniform(-top.w / 2 + 0.06, top.w / 2 - 0.06), rng.uniform(-top.d / 2 + 0.06, top.d / 2 - 0.06)
            if all((x - a) ** 2 + (y - b) ** 2 > (r + 0.08) ** 2 for a, b, r in placed):
                it = make(rng, compose(top.M, x, y, 0, yaw=rng.uniform(0, 2 * np.pi)))
                placed.append((x, y, 0.5 * max(it.size[:2])))
                P += it.panels
                break
    return P
