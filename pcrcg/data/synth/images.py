"""Printed pictures for generated rooms: photos, maps and pages made from files that installed
packages ship, so nothing is downloaded and the same install gives the same bank.

* the sample images matplotlib ships (a photo, a logo, a drawing), found through
  ``importlib.metadata`` rather than by importing a sample-data API;
* its elevation maps, coloured like printed maps;
* pages of text, tables and charts drawn with matplotlib's Agg renderer from a fixed seed
  (calendars, notices, plots: the high-contrast print of real offices and kitchens).

Every image is float32 (H, W, 3) in [0, 1]. The bank is built once per process.
"""

from __future__ import annotations

import functools
import importlib.metadata as md
import io

import numpy as np

_PHOTOS = ("grace_hopper.jpg", "Minduka_Present_Blue_Pack.png", "logo2.png")
_MAPS = ("jacksboro_fault_dem.npz", "topobathy.npz")
_N_PAGES = 8


def _sample_file(name: str) -> str | None:
    try:
        files = md.files("matplotlib") or []
    except md.PackageNotFoundError:
        return None
    for f in files:
        if f.name == name and "sample_data" in str(f):
            return str(f.locate())
    return None


def _photo(path: str) -> np.ndarray | None:
    import cv2

    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        return None
    return (img[:, :, ::-1].astype(np.float32) / 255.0)


def _map(path: str, cmap: str) -> np.ndarray | None:
    import matplotlib

    with np.load(path, allow_pickle=False) as z:
        key = next((k for k in z.files if z[k].ndim == 2), None)
        if key is None:
            return None
        dem = z[key].astype(np.float64)
    dem = (dem - dem.min()) / max(np.ptp(dem), 1e-9)
    return matplotlib.colormaps[cmap](dem)[:, :, :3].astype(np.float32)


def _page(seed: int) -> np.ndarray:
    """A page of text, a table or a chart, rendered off-screen (Agg)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    rng = np.random.default_rng([seed, 4099])
    fig = Figure(figsize=(3, 4), dpi=80)
    bg = rng.uniform(0.8, 1.0, 3)
    fig.patch.set_facecolor(bg)
    kind = seed % 4
    words = ["MENU", "NOTICE", "MEETING", "KITCHEN", "LAB", "ROOM 214", "SALE", "EXIT", "AGENDA",
             "PLAN", "TEAM", "COFFEE", "MONDAY", "2013", "SCAN", "FLOOR 3", "HOTEL", "STUDY"]
    if kind == 0:  # a chart
        ax = fig.add_axes([0.15, 0.15, 0.8, 0.6])
        x = np.arange(12)
        for _ in range(int(rng.integers(1, 4))):
            ax.plot(x, rng.normal(0, 1, 12).cumsum(), lw=2, color=rng.uniform(0, 0.8, 3))
        ax.bar(x, rng.uniform(0, 3, 12), color=rng.uniform(0.2, 0.9, 3), alpha=0.6)
        fig.text(0.1, 0.85, str(rng.choice(words)), fontsize=22, weight="bold", color=rng.uniform(0, 0.5, 3))
    elif kind == 1:  # a calendar grid
        ax = fig.add_axes([0.05, 0.05, 0.9, 0.7])
        ax.set_axis_off()
        for r in range(5):
            for c in range(7):
                ax.text(c / 7, 1 - r / 5, str(r * 7 + c + 1), fontsize=11, transform=ax.transAxes)
        ax.imshow(rng.uniform(0, 1, (3, 4, 3)), extent=(0, 1, 1.05, 1.4), transform=ax.transAxes)
        fig.text(0.1, 0.88, str(rng.choice(words)), fontsize=20, weight="bold")
    elif kind == 2:  # a notice: lines of text
        for k in range(int(rng.integers(6, 12))):
            n = int(rng.integers(2, 5))
            line = " ".join(str(w) for w in rng.choice(words, n))
            fig.text(0.06, 0.92 - k * 0.08, line, fontsize=float(rng.uniform(9, 16)), color=rng.uniform(0, 0.4, 3))
    else:  # a poster: shapes and a title
        ax = fig.add_axes([0, 0, 1, 1])
        ax.set_axis_off()
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        for _ in range(int(rng.integers(4, 10))):
            xy = rng.uniform(0, 1, 2)
            ax.add_patch(matplotlib.patches.Circle(xy, rng.uniform(0.05, 0.2), color=rng.uniform(0, 1, 3)))
        ax.text(0.08, 0.08, str(rng.choice(words)), fontsize=26, weight="bold", color=rng.uniform(0, 0.3, 3))
    buf = io.BytesIO()
    fig.savefig(buf, format="rgba", dpi=80, facecolor=bg)
    w, h = fig.canvas.get_width_height()
    arr = np.frombuffer(buf.getvalue(), np.uint8).reshape(h, w, 4)
    return arr[:, :, :3].astype(np.float32) / 255.0


@functools.lru_cache(maxsize=1)
def image_bank() -> tuple[np.ndarray, ...]:
    """The printed pictures: (H, W, 3) float32 arrays in [0, 1]; pages only where matplotlib's
    sample files are missing."""
    out = []
    for name in _PHOTOS:
        p = _sample_file(name)
        img = _photo(p) if p else None
        if img is not None:
            out.append(img)
    for name, cmap in zip(_MAPS, ("terrain", "gist_earth")):
        p = _sample_file(name)
        img = _map(p, cmap) if p else None
        if img is not None:
            out.append(img)
    out += [_page(k) for k in range(_N_PAGES)]
    return tuple(out)
