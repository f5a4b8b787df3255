"""Procedural albedo textures evaluated on surface coordinates (metres), fully vectorised.

A :class:`Texture` maps surface coordinates ``(u, v)`` (N,) to albedo (N, 3) in [0, 1].
Families: ``plain``, ``noise`` (multi-octave value noise), ``stripes``, ``checks``, ``shapes``
(random discs and squares on a jittered grid), ``gradient`` (triangle-wave ramp with grain), and the
materials of real rooms: ``wood`` (grain lines bent by noise), ``fabric`` (a fine weave with
pilling), ``tiles`` (jittered tiles and grout), ``paint`` (near-plain with roller marks) and
``image`` (a printed picture: a photo, a map, a page of text and charts; see
:mod:`pcrcg.data.synth.images`) stretched over the surface.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FAMILIES = ("plain", "noise", "stripes", "checks", "shapes", "gradient", "wood", "fabric", "tiles", "paint", "image")


def _hash01(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer lattice coordinates."""
    h = (ix.astype(np.int64) * 73856093) ^ (iy.astype(np.int64) * 19349663) ^ (int(seed) * 83492791)
    h = h.astype(np.uint64)
    h ^= h >> np.uint64(33)
    h *= np.uint64(0xFF51AFD7ED558CCD)
    h ^= h >> np.uint64(33)
    h *= np.uint64(0xC4CEB9FE1A85EC53)
    h ^= h >> np.uint64(33)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def value_noise(u: np.ndarray, v: np.ndarray, scale: float, seed: int, octaves: int = 3) -> np.ndarray:
    """Smooth value noise in [0, 1] with feature size ``scale`` metres."""
    total = np.zeros_like(u, dtype=np.float64)
    amp_sum = 0.0
    amp = 1.0
    for o in range(octaves):
        x = u / scale * (2**o)
        y = v / scale * (2**o)
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        fx = fx * fx * (3 - 2 * fx)
        fy = fy * fy * (3 - 2 * fy)
        s = seed * 31 + o
        a = _hash01(x0, y0, s)
        b = _hash01(x0 + 1, y0, s)
        c = _hash01(x0, y0 + 1, s)
        d = _hash01(x0 + 1, y0 + 1, s)
        total += amp * ((a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy)
        amp_sum += amp
        amp *= 0.5
    return total / amp_sum


@dataclass
class Texture:
    family: str
    colors: np.ndarray  # (3, 3) palette, rows in [0, 1]
    scale: float = 0.2  # metres: period / cell size / noise feature size
    angle: float = 0.0  # radians, orientation of stripes / gradients / checks
    seed: int = 0
    grain: float = 0.04  # amplitude of fine noise added to every family
    params: dict = field(default_factory=dict)

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Albedo (N, 3) in [0, 1] at surface coordinates u, v (N,)."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        ca, sa = np.cos(self.angle), np.sin(self.angle)
        ru, rv = ca * u + sa * v, -sa * u + ca * v
        c0, c1, c2 = self.colors
        fam = self.family
        if fam == "plain":
            out = np.broadcast_to(c0, (u.size, 3)).copy()
        elif fam == "noise":
            n = value_noise(u, v, self.scale, self.seed, octaves=4)
            t = np.clip((n - 0.5) * 2.2 + 0.5, 0, 1)[:, None]
            out = c0 * (1 - t) + c1 * t
        elif fam == "stripes":
            duty = self.params.get("duty", 0.5)
            phase = (ru / self.scale) % 1.0
            out = np.where((phase < duty)[:, None], c0, c1)
            # a thin third-colour pin stripe makes the pattern non-periodic-looking
            out = np.where((np.abs(phase - duty) < 0.06)[:, None], c2, out)
        elif fam == "checks":
            k = (np.floor(ru / self.scale) + np.floor(rv / self.scale)).astype(np.int64) % 2
            out = np.where((k == 0)[:, None], c0, c1)
        elif fam == "shapes":
            cu, cv = np.floor(ru / self.scale), np.floor(rv / self.scale)
            fu, fv = ru / self.scale - cu, rv / self.scale - cv
            r = 0.18 + 0.25 * _hash01(cu, cv, self.seed + 1)
            ou = 0.5 + (_hash01(cu, cv, self.seed + 2) - 0.5) * (1 - 2 * r)
            ov = 0.5 + (_hash01(cu, cv, self.seed + 3) - 0.5) * (1 - 2 * r)
            kind = _hash01(cu, cv, self.seed + 4)
            du, dv = fu - ou, fv - ov
            inside = np.where(kind < 0.5, du * du + dv * dv < r * r, np.maximum(np.abs(du), np.abs(dv)) < r)
            inside &= _hash01(cu, cv, self.seed + 5) < 0.85
            pick = _hash01(cu, cv, self.seed + 6) < 0.5
            shape_col = np.where(pick[:, None], c1, c2)
            out = np.where(inside[:, None], shape_col, c0)
        elif fam == "gradient":
            t = np.abs(((ru / self.scale) % 2.0) - 1.0)[:, None]
            out = c0 * (1 - t) + c1 * t
        elif fam == "wood":  # grain along u, rings bent by low-frequency noise, darker late-wood lines
            bend = value_noise(ru * 0.25, rv * 2.0, self.scale * 4, self.seed, octaves=2)
            ring = ((rv + 0.6 * self.scale * 4 * bend) / self.scale) % 1.0
            line = np.exp(-((ring - 0.5) ** 2) / 0.004)
            fine = value_noise(ru * 0.1, rv * 3.0, self.scale, self.seed + 3, octaves=2)
            t = np.clip(0.55 * line + 0.45 * fine, 0, 1)[:, None]
            out = c0 * (1 - t) + c1 * t
            plank = self.params.get("plank", 0.0)
            if plank > 0:  # floor boards: seams across and along
                seam = (np.abs((rv / plank) % 1.0) < 0.04) | (np.abs(((ru + 1.3 * np.floor(rv / plank)) / (6 * plank)) % 1.0) < 0.008)
                out = np.where(seam[:, None], c2 * 0.5, out)
        elif fam == "fabric":  # weave + slow colour variation + pilling
            s = self.scale * 0.05
            weave = 0.5 + 0.5 * np.sin(2 * np.pi * ru / s) * np.sin(2 * np.pi * rv / s)
            slow = value_noise(u, v, self.scale * 3, self.seed, octaves=3)
            t = np.clip(0.08 * weave + 0.92 * slow, 0, 1)[:, None]  # a sub-pixel weave: faint
            out = c0 * (1 - t) + c1 * t
        elif fam == "tiles":  # square tiles with a per-tile shade and grout lines
            cu, cv = np.floor(ru / self.scale), np.floor(rv / self.scale)
            fu, fv = ru / self.scale - cu, rv / self.scale - cv
            shade = _hash01(cu, cv, self.seed)[:, None]
            out = c0 * (1 - 0.5 * shade) + c1 * 0.5 * shade
            grout = (fu < 0.04) | (fv < 0.04)
            out = np.where(grout[:, None], c2, out)
        elif fam == "paint":  # nearly plain: roller marks and slow stains
            n = value_noise(u, v, self.scale, self.seed, octaves=3)
            streak = value_noise(ru * 0.15, rv * 3.0, self.scale, self.seed + 1, octaves=2)
            t = np.clip(0.5 + 1.2 * (0.6 * n + 0.4 * streak - 0.5), 0, 1)[:, None]
            out = c0 * (1 - t) + c1 * t
        elif fam == "image":
            out = _sample_image(self.params["image"], u, v, self.params["extent"])
        else:
            raise ValueError(f"unknown texture family {fam!r}; allowed {FAMILIES}")
        if self.grain > 0:  # grain on 4 cm cells (no interpolation: cheap); finer cells alias at the
            # cameras' ~1 cm pixel footprint and flicker from frame to frame (no real surface does)
            g = _hash01(np.floor(u * 25.0), np.floor(v * 25.0), self.seed + 97) - 0.5
            out = out * (1.0 + self.grain * 2 * g[:, None])
        return np.clip(out, 0.0, 1.0).astype(np.float32)


def _sample_image(img: np.ndarray, u: np.ndarray, v: np.ndarray, extent) -> np.ndarray:
    """Bilinear lookup of an (H, W, 3) float image stretched over ``extent`` (w, h) metres
    (u right, v up), repeated beyond it."""
    H, W = img.shape[:2]
    x = (u / extent[0] % 1.0) * (W - 1)
    y = (1.0 - v / extent[1] % 1.0) * (H - 1)
    x0 = np.clip(np.floor(x).astype(np.int64), 0, W - 2)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, H - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    a, b = img[y0, x0], img[y0, x0 + 1]
    c, d = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def image_texture(rng: np.random.Generator, extent, kind: str = "poster") -> Texture:
    """A printed picture from the bank (:func:`pcrcg.data.synth.images.image_bank`) stretched over
    a surface of ``extent`` (w, h) metres."""
    from pcrcg.data.synth.images import image_bank

    bank = image_bank()
    img = bank[int(rng.integers(0, len(bank)))]
    if rng.random() < 0.6:  # a crop, so that posters of one scene differ
        H, W = img.shape[:2]
        ch, cw = int(H * rng.uniform(0.5, 1.0)), int(W * rng.uniform(0.5, 1.0))
        y0, x0 = int(rng.integers(0, H - ch + 1)), int(rng.integers(0, W - cw + 1))
        img = img[y0 : y0 + ch, x0 : x0 + cw]
    tint = rng.uniform(0.85, 1.1, size=3)
    img = np.clip(np.ascontiguousarray(img) * tint, 0, 1).astype(np.float32)
    return Texture("image", np.zeros((3, 3)), 1.0, 0.0, int(rng.integers(0, 2**31 - 1)), 0.02,
                   {"image": img, "extent": (float(extent[0]), float(extent[1]))})


def random_palette(rng: np.random.Generator, contrast: float) -> np.ndarray:
    """Three colours; ``contrast`` in [0, 1] sets how far apart they are."""
    base = rng.uniform(0.25, 0.85, size=3)
    cols = [base]
    for _ in range(2):
        delta = rng.normal(size=3)
        delta = delta / (np.linalg.norm(delta) + 1e-9) * contrast * rng.uniform(0.5, 0.9)
        cols.append(np.clip(base + delta, 0.03, 0.97))
    return np.stack(cols)


def material(rng: np.random.Generator, kind: str) -> Texture:
    """A real-room material for a surface kind: ``wood``, ``fabric``, ``paint``, ``tiles``,
    ``metal``, ``plastic``, ``floor`` (wood boards, tiles or carpet), ``wall`` (paint, sometimes tiles)."""
    seed = int(rng.integers(0, 2**31 - 1))
    angle = float(rng.choice([0.0, np.pi / 2])) + float(rng.normal(0, 0.02))
    if kind == "wood":
        base = np.array([0.55, 0.36, 0.2]) * rng.uniform(0.6, 1.4) + rng.normal(0, 0.04, 3)
        cols = np.stack([base, base * rng.uniform(0.55, 0.8), base * 0.4])
        return Texture("wood", np.clip(cols, 0.03, 0.95), float(rng.uniform(0.015, 0.04)), angle, seed, 0.03)
    if kind == "fabric":
        return Texture("fabric", random_palette(rng, 0.18), float(rng.uniform(0.05, 0.15)), angle, seed, 0.05)
    if kind == "paint":
        pal = random_palette(rng, 0.06)
        pal = np.clip(pal * rng.uniform(0.9, 1.25), 0, 0.97)
        return Texture("paint", pal, float(rng.uniform(0.3, 1.0)), angle, seed, 0.02)
    if kind == "tiles":
        return Texture("tiles", random_palette(rng, 0.12), float(rng.choice([0.1, 0.15, 0.2, 0.3])), angle, seed, 0.02)
    if kind in ("metal", "plastic"):
        pal = random_palette(rng, 0.05 if kind == "plastic" else 0.12)
        return Texture("noise", pal, float(rng.uniform(0.05, 0.3)), angle, seed, 0.03)
    if kind == "floor":
        pick = rng.choice(["wood", "tiles", "carpet"], p=[0.45, 0.3, 0.25])
        if pick == "wood":
            t = material(rng, "wood")
            t.params["plank"] = float(rng.uniform(0.1, 0.2))
            t.scale *= 2
            return t
        if pick == "tiles":
            return material(rng, "tiles")
        return Texture("fabric", random_palette(rng, 0.15), float(rng.uniform(0.1, 0.3)), angle, seed, 0.06)
    if kind == "wall":
        return material(rng, "tiles") if rng.random() < 0.08 else material(rng, "paint")
    raise ValueError(f"unknown material {kind!r}")


def random_texture(rng: np.random.Generator, kind: str) -> Texture:
    """A texture typical of a surface kind: ``wall``, ``floor``, ``ceiling``, ``furniture``, ``poster``, ``rug``."""
    seed = int(rng.integers(0, 2**31 - 1))
    angle = float(rng.uniform(0, np.pi))
    if kind in ("wall", "ceiling"):  # mostly low-contrast, rarely perfectly plain (like plaster and paint)
        fam = rng.choice(["plain", "noise", "gradient"], p=[0.15, 0.6, 0.25])
        return Texture(str(fam), random_palette(rng, 0.28), float(rng.uniform(0.15, 0.8)), angle, seed, 0.06)
    if kind == "floor":
        fam = rng.choice(["stripes", "checks", "noise"], p=[0.4, 0.3, 0.3])
        return Texture(str(fam), random_palette(rng, 0.45), float(rng.uniform(0.1, 0.4)), angle, seed, 0.08,
                       {"duty": float(rng.uniform(0.3, 0.7))})
    if kind == "furniture":
        fam = rng.choice(["plain", "noise", "stripes", "checks"], p=[0.15, 0.5, 0.2, 0.15])
        return Texture(str(fam), random_palette(rng, 0.45), float(rng.uniform(0.04, 0.25)), angle, seed, 0.08)
    if kind in ("poster", "rug"):
        fam = rng.choice(["noise", "stripes", "checks", "shapes", "gradient"])
        scale = float(rng.uniform(0.04, 0.2))
        return Texture(str(fam), random_palette(rng, 0.9), scale, angle, seed, 0.05,
                       {"duty": float(rng.uniform(0.3, 0.7))})
    raise ValueError(f"unknown surface kind {kind!r}")
