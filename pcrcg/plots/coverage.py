"""The paper's color-coverage figure: a fragment's points, colored where they got a feature.

``python -m pcrcg.plots.coverage data.root=data/synthmatch-tiny out=reports/color_coverage.png``

One panel per number of views (1, 2, 3: first, first+last, first+last+middle frame). Points that
receive a 2D feature keep their color; points that receive none are black (as in the paper).
Other keys: ``split=val pair=0 fragment=tgt|src projection=implicit|explicit window_size=11
depth_tolerance=0.1 image_size=null point_size=2 method=sift cache_dir=cache/matches``.
Without ``data.root`` the figure is drawn for a toy pair (:mod:`pcrcg.testing.scenes`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pcrcg.geometry import invert, look_at, project, transform_points
from pcrcg.plots import no_ticks, pyplot, save_figure


def coverage_masks(sample: Any, fragment: str = "tgt", projection: str = "implicit", window_size: int = 11,
                   depth_tolerance: float = 0.1, image_size: Sequence[int] | None = None, matcher: Any = None,
                   cache: Any = None, views: Sequence[int] = (1, 2, 3)) -> dict[int, np.ndarray]:
    """{n_views: covered (N,) bool} for one fragment of a pair."""
    import torch

    from pcrcg.lifting import ColorLifter, LiftingConfig
    from pcrcg.lifting.projection import keypoints_per_view
    from pcrcg.vision.matching import MatcherConfig, match_views

    pts = np.asarray(sample.src_points if fragment == "src" else sample.tgt_points, np.float32)
    fviews = sample.src_views if fragment == "src" else sample.tgt_views
    weights = None
    if projection == "explicit":
        nv = max(views)
        m = match_views(sample.src_views[:nv], sample.tgt_views[:nv], matcher or MatcherConfig(), cache,
                        getattr(sample, "transform", None))
        skp, tkp = keypoints_per_view(m, min(nv, len(sample.src_views)), min(nv, len(sample.tgt_views)))
        weights = skp if fragment == "src" else tkp
    out = {}
    for v in views:
        cfg = LiftingConfig(projection, "none", int(v), int(window_size), depth_tolerance,
                            image_size=tuple(image_size) if image_size else None)
        out[int(v)] = ColorLifter(cfg).coverage(torch.from_numpy(pts), fviews, weights).numpy()
    return out


def overview_camera(points: np.ndarray) -> np.ndarray:
    """A camera-to-fragment pose behind and above the fragment's first camera, looking at the points.

    The fragment frame is the first camera's (x right, y down, z forward), so "up" is -y.
    """
    centre = np.median(points, axis=0)
    extent = np.percentile(np.linalg.norm(points - centre, axis=1), 90)
    eye = centre + np.array([0.0, -0.9, -1.1]) * (1.2 * extent + 0.5)
    return look_at(eye, centre, up=(0.0, -1.0, 0.0))


def draw(points: np.ndarray, colors: np.ndarray | None, masks: dict[int, np.ndarray], out: str | Path,
         title: str = "", point_size: float = 2.0, size: tuple[int, int] = (480, 360)) -> Path:
    """Render one panel per entry of ``masks`` (splatted points, far to near) into a PNG."""
    plt = pyplot()
    W, H = size
    pose = overview_camera(points)
    K = np.array([[0.8 * W, 0, W / 2], [0, 0.8 * W, H / 2], [0, 0, 1.0]])
    pc = transform_points(invert(pose), points.astype(np.float64))
    uv, z = project(pc, K)
    order = np.argsort(-z)
    ok = z[order] > 0.05
    order = order[ok]
    base = np.asarray(colors, np.float32) if colors is not None and np.asarray(colors).max() > 0 else None
    if base is None:
        base = np.tile(np.array([[0.95, 0.55, 0.15]], np.float32), (len(points), 1))
    n = len(masks)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.6), dpi=110)
    axes = np.atleast_1d(axes)
    for ax, (k, cov) in zip(axes, sorted(masks.items())):
        col = np.where(cov[:, None], base, 0.0)
        ax.scatter(uv[order, 0], uv[order, 1], c=col[order], s=point_size, marker="s", linewidths=0)
        ax.set_xlim(0, W)
        ax.set_ylim(H, 0)
        ax.set_aspect("equal")
        no_ticks(ax)
        ax.set_facecolor("#e8e8e8")
        ax.set_title(f"{k} view{'s' if k > 1 else ''}: {100 * cov.mean():.1f}% covered", fontsize=10)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out)


def main(argv: Sequence[str] | None = None) -> Path:
    import sys

    from omegaconf import OmegaConf

    from pcrcg.vision.matching import MatchCache, MatcherConfig

    args = OmegaConf.from_dotlist(list(sys.argv[1:] if argv is None else argv))
    root = OmegaConf.select(args, "data.root")
    split = str(args.get("split", "val"))
    k = int(args.get("pair", 0))
    fragment = str(args.get("fragment", "tgt"))
    if fragment not in ("src", "tgt"):
        raise SystemExit(f"fragment must be src or tgt, got {fragment}")
    if root is None:
        from pcrcg.testing.scenes import make_pair

        sample = make_pair(k)
        where = f"toy pair {k}"
    else:
        from pcrcg.data.dataset import PairDataset

        ds = PairDataset(root, split, n_views=3)
        sample = ds[k]
        where = f"{root} {split} pair {k} ({sample.scene} {sample.i}-{sample.j})"
    projection = str(args.get("projection", "implicit"))
    mnode = {key: args[key] for key in ("method", "ratio", "mutual", "ransac_threshold", "max_keypoints",
                                        "min_matches", "pairs") if key in args}
    cache_dir = args.get("cache_dir", "cache/matches" if root else None)
    masks = coverage_masks(sample, fragment, projection, int(args.get("window_size", 11)),
                           float(args.get("depth_tolerance", 0.1)), args.get("image_size", None),
                           MatcherConfig.from_cfg(mnode), MatchCache(cache_dir) if cache_dir else None)
    pts = sample.src_points if fragment == "src" else sample.tgt_points
    cols = sample.src_colors if fragment == "src" else sample.tgt_colors
    frag_id = sample.j if fragment == "src" else sample.i
    title = f"Color coverage ({projection}), fragment {frag_id} of {where}"
    out = draw(np.asarray(pts), np.asarray(cols), masks, args.get("out", "reports/color_coverage.png"), title,
               float(args.get("point_size", 2.0)))
    print(" ".join(f"views={v}: {100 * m.mean():.1f}%" for v, m in sorted(masks.items())))
    print(f"wrote {out}")
    return out


if __name__ == "__main__":
    main()
