"""The outputs of ``python -m pcrcg.data.stats``: a Markdown table, its JSON, and a picture."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from pcrcg.data.layout import BENCHMARKS
from pcrcg.plots import pyplot, save_figure

DASH = "–"
# coarse overlap bins shown in the table (the JSON keeps the 10 fine bins of measures.OVERLAP_EDGES)
COARSE = ((0.0, 0.1), (0.1, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 1.0))


def _num(v: Any, fmt: str = "{:.2f}") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return DASH
    return fmt.format(v)


def _range(s: dict | None, fmt: str = "{:.2f}", lo: str = "min", hi: str = "max", mid: str = "median") -> str:
    if not s or s.get(mid) is None:
        return DASH
    return f"{fmt.format(s[mid])} ({fmt.format(s[lo])}–{fmt.format(s[hi])})"


def _sides(v: Sequence[float] | None) -> str:
    if v is None or any(x is None or not math.isfinite(x) for x in v):
        return DASH
    return " × ".join(f"{x:.2f}" for x in v)


def _coarse(counts: Sequence[int]) -> list[int]:
    edges = [round(0.1 * k, 1) for k in range(len(counts) + 1)]
    out = []
    for lo, hi in COARSE:
        out.append(int(sum(c for c, e in zip(counts, edges) if lo - 1e-9 <= e < hi - 1e-9)))
    return out


def _overlap(h: dict | None) -> str:
    if not h:
        return DASH
    med = _num(h.get("median"))
    return f"{h['n']} pairs, median {med}: " + " / ".join(str(c) for c in _coarse(h["counts"]))


def _fpfh(c: dict, b: str) -> str:
    f = c.get("fpfh")
    if not f or b not in f:
        return DASH
    e = f[b]
    if not e.get("counted"):
        return f"{DASH} (0 counted of {e['pairs']} pairs)"
    return f"{_num(e['rr'], '{:.1f}')}% ({e['success']}/{e['counted']} counted; {e['pairs']} of {e['listed']} pairs)"


def _motion(c: dict, b: str) -> str:
    h = (c.get("overlap") or {}).get(b)
    if not h or not h.get("rotation_deg") or h["rotation_deg"].get("median") is None:
        return DASH
    r, t = h["rotation_deg"], h["translation_m"]
    return f"{r['median']:.0f} ({r['p10']:.0f}–{r['p90']:.0f}) deg; {t['median']:.2f} ({t['p10']:.2f}–{t['p90']:.2f}) m"


def _fpfh_ir(c: dict, b: str) -> str:
    e = (c.get("fpfh") or {}).get(b)
    if not e or e.get("ir") is None:
        return DASH
    return f"{_num(e['ir'], '{:.1f}')}% / {_num(e.get('fmr'), '{:.1f}')}%"


def _sift(c: dict, key: str, what: str) -> str:
    s = c.get("sift")
    if not s:
        return DASH
    e = s[key]
    size = e["size"] if e["size"] != "native" else "/".join(s["native_size"])
    if what == "keypoints":
        k = e["keypoints"]
        return f"{_num(k['mean'], '{:.0f}')} ({_num(k['p10'], '{:.0f}')}–{_num(k['p90'], '{:.0f}')}) at {size}"
    m = e["matches"]
    return (f"{_num(m['mean'], '{:.1f}')} (median {_num(m['median'], '{:.0f}')}; "
            f"{100 * e['verified_share']:.0f}% verified) at {size}")


def _holes(c: dict) -> str:
    d = c.get("depth")
    if not d or d.get("mean") is None:
        return DASH
    return f"{100 * d['mean']:.1f}% ({100 * d['p10']:.1f}–{100 * d['p90']:.1f}%), {d['frames']} frames"


def _by_covis(c: dict) -> str:
    s = c.get("sift") or {}
    bins = s.get("grid_by_covisibility")
    if not bins or not (s.get("covisibility") or {}).get("n"):
        return DASH
    return " / ".join(DASH if b["mean"] is None else f"{b['mean']:.1f} ({b['n']})" for b in bins)


def _by_benchmark(c: dict) -> str:
    per = (c.get("sift") or {}).get("grid_by_benchmark")
    if not per:
        return DASH
    return " / ".join(DASH if per.get(b, {}).get("mean") is None else f"{per[b]['mean']:.1f} ({per[b]['n']})"
                      for b in BENCHMARKS)


def _depth_m(c: dict) -> str:
    m = (c.get("depth") or {}).get("median_m")
    if not m or m.get("median") is None:
        return DASH
    return f"{m['median']:.2f} ({m['p10']:.2f}–{m['p90']:.2f})"


def _below(c: dict, b: str) -> str:
    s = c.get("sampling") or {}
    if not (s.get(b) or {}).get("pairs"):
        return DASH
    below = s[b]["below"]
    shares = " · ".join(f"{n}: {100 * below[n]:.0f}%" for n in sorted(below, key=int, reverse=True))
    return f"{shares} ({s[b]['pairs']} pairs; median {s[b]['smaller_points']['median']:,.0f} points)"


def _frag(c: dict) -> dict:
    return c.get("fragments") or {}


ROWS: list[tuple[str, Callable[[dict], str]]] = [
    ("fragments (scenes; measured)", lambda c: f"{_frag(c)['count']} ({_frag(c)['scenes']}; {_frag(c)['measured']})"),
    ("points / fragment at 2.5 cm: mean (p10–p90)", lambda c: (
        f"{_num(_frag(c)['points']['mean'], '{:,.0f}')} ({_num(_frag(c)['points']['p10'], '{:,.0f}')}–"
        f"{_num(_frag(c)['points']['p90'], '{:,.0f}')})")),
    ("extent, PCA box, 2–98%, m (sorted; median)", lambda c: _sides(_frag(c).get("extent_pca_median"))),
    ("extent, x y z box in the fragment frame, 2–98%, m (median)", lambda c: _sides(_frag(c).get("extent_xyz_median"))),
    ("planarity: 4 RANSAC planes, 2 cm, 5 cm voxels (median, min–max)", lambda c: _range(_frag(c).get("planarity"))),
    ("normal-orientation entropy, bits (median, min–max)", lambda c: _range(_frag(c).get("normal_entropy"))),
    *[(f"{b} pairs: overlap median; count 0–10/10–30/30–50/50–70/70–100%",
       (lambda b: lambda c: _overlap((c.get("overlap") or {}).get(b)))(b)) for b in BENCHMARKS],
    *[(f"{b} pairs: relative rotation; translation of the first cameras: median (p10–p90)",
       (lambda b: lambda c: _motion(c, b))(b)) for b in BENCHMARKS],
    ("train pairs: overlap median; count 0–10/10–30/30–50/50–70/70–100%",
     lambda c: _overlap((c.get("overlap") or {}).get("train"))),
    *[(f"{b} pairs whose smaller fragment has fewer than N points at the profile's model voxel (sampled "
       "uniformly with replacement there, not by overlap): share per N (pairs; median smaller fragment)",
       (lambda b: lambda c: _below(c, b))(b)) for b in BENCHMARKS],
    *[(f"FPFH + RANSAC RR, {b} (scene mean; registered/counted; pairs run of listed)",
       (lambda b: lambda c: _fpfh(c, b))(b)) for b in BENCHMARKS],
    *[(f"FPFH correspondences, {b}: inlier ratio (10 cm) / feature-match recall, mean over pairs",
       (lambda b: lambda c: _fpfh_ir(c, b))(b)) for b in BENCHMARKS],
    ("SIFT keypoints / image, projection grid: mean (p10–p90)", lambda c: _sift(c, "grid", "keypoints")),
    ("SIFT keypoints / image, native size: mean (p10–p90)", lambda c: _sift(c, "native", "keypoints")),
    ("verified 2D matches / view pair, projection grid: mean", lambda c: _sift(c, "grid", "matches")),
    ("verified 2D matches / view pair, native size: mean", lambda c: _sift(c, "native", "matches")),
    ("verified 2D matches / view pair, projection grid, by the pair's co-visibility 0–30 / 30–50 / 50–100%: "
     "mean (view pairs)", _by_covis),
    ("verified 2D matches / view pair, projection grid, of 3DMatch / 3DLoMatch pairs: mean (view pairs)",
     _by_benchmark),
    ("view pairs (first-first, last-last of each pair run)",
     lambda c: DASH if not c.get("sift") else f"{c['sift']['view_pairs']} ({c['sift']['view_pairs_skipped']} without frames)"),
    ("depth holes: share of zero pixels, mean (p10–p90)", _holes),
    ("depth per frame, median over its pixels with depth, m: median (p10–p90)", _depth_m),
]


def markdown_table(columns: Sequence[dict]) -> str:
    """One column per data set, one row per measure; "–" where a data set cannot be measured."""
    head = "| measure | " + " | ".join(c["name"] for c in columns) + " |"
    sep = "| --- |" + " --- |" * len(columns)
    lines = [head, sep]
    for label, fn in ROWS:
        cells = []
        for c in columns:
            try:
                cells.append(fn(c))
            except (KeyError, TypeError):
                cells.append(DASH)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, tuple):
        return list(o)
    return str(o)


def _clean(o: Any) -> Any:
    """NaN/inf -> None, recursively (JSON has no NaN)."""
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def write_outputs(columns: Sequence[dict], settings: dict, out: str | Path, notes: str = "") -> tuple[Path, Path]:
    """``<out>.md`` (the table and how it was measured) and ``<out>.json`` (every number)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    md, js = out.with_name(out.name + ".md"), out.with_name(out.name + ".json")
    md.write_text("# Data sets side by side (`python -m pcrcg.data.stats`)\n\n" + markdown_table(columns)
                  + ("\n" + notes if notes else ""))
    js.write_text(json.dumps(_clean({"settings": settings, "columns": list(columns)}), indent=1,
                             default=_json_default) + "\n")
    return md, js


# --------------------------------------------------------------------------- picture


def _panel(ax, pts: np.ndarray, cols: np.ndarray | None, view: str, lims) -> None:
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    if view == "top":  # from above (the fragment frame's y points down): x right, z forward up
        h, v, order = x, z, np.argsort(-y)  # highest points (small y) drawn last
    else:  # from the left (-x): z to the right, height (-y) up; nearest (small x) drawn last
        h, v, order = z, -y, np.argsort(-x)
    if cols is not None:
        c = np.clip(cols[order], 0, 1)
        ax.scatter(h[order], v[order], c=c, s=1.2, marker="s", linewidths=0, rasterized=True)
    else:
        ax.scatter(h[order], v[order], c=-y[order], cmap="viridis", s=1.2, marker="s", linewidths=0,
                   rasterized=True)
    ax.set_xlim(*lims[0])
    ax.set_ylim(*lims[1])
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6, length=2)


def _lims(values: list[np.ndarray], pad: float = 0.1) -> tuple[float, float]:
    """The union of the fragments' 0.2-99.8 percentile ranges (a few stray points do not count)."""
    lo = min(float(np.percentile(v, 0.2)) for v in values)
    hi = max(float(np.percentile(v, 99.8)) for v in values)
    return lo - pad, hi + pad


def picture(previews: Sequence[tuple[str, list[dict]]], out: str | Path) -> Path:
    """A few fragments of each data set side by side: per fragment a top-down and a side view, on
    the same metric axes everywhere (colored by their colors, or by height where they have none)."""
    plt = pyplot()
    rows = [(n, p) for n, p in previews if p]
    k = max(len(p) for _, p in rows)
    allp = [f["points"] for _, p in rows for f in p]
    top = (_lims([q[:, 0] for q in allp]), _lims([q[:, 2] for q in allp]))
    side = (_lims([q[:, 2] for q in allp]), _lims([-q[:, 1] for q in allp]))
    fig, axes = plt.subplots(len(rows), 2 * k, figsize=(2.6 * 2 * k, 2.9 * len(rows)), squeeze=False)
    for r, (name, frags) in enumerate(rows):
        for j in range(k):
            at, asd = axes[r, 2 * j], axes[r, 2 * j + 1]
            if j >= len(frags):
                at.axis("off")
                asd.axis("off")
                continue
            f = frags[j]
            _panel(at, f["points"], f["colors"], "top", top)
            _panel(asd, f["points"], f["colors"], "side", side)
            col = "color" if f["colors"] is not None else "height (-y)"
            at.set_xlabel("x (m)", fontsize=6, labelpad=1)
            at.set_ylabel("z (m)", fontsize=6, labelpad=1)
            asd.set_xlabel("z (m)", fontsize=6, labelpad=1)
            asd.set_ylabel("-y (m)", fontsize=6, labelpad=1)
            at.set_title(f"{name}\n{f['scene']} cloud_bin_{f['index']}: top (x, z)", fontsize=7)
            asd.set_title(f"{len(f['points'])} pts at 2.5 cm, {col}\nside (z, -y)", fontsize=7)
    fig.suptitle("Fragments side by side (metres, same axes in every panel; fragment frame = first camera)",
                 fontsize=9)
    fig.tight_layout()
    return save_figure(fig, out, dpi=110)
