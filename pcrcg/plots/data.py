"""Pictures of a data set: RGB-D frames and fragments, for a person to look at.

``python -m pcrcg.plots.data ROOT [--scene S] [--out FILE.png]`` writes one PNG: two color frames
with their depth, two fragments rendered from their first camera and from above, and a pair
aligned by its ground truth (one fragment tinted orange, the other blue).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pcrcg.data.layout import Layout, frame_paths, read_cloud, read_color, read_depth, read_fragment_info
from pcrcg.geometry import transform_points
from pcrcg.plots import no_ticks, pyplot, save_figure


def splat(points: np.ndarray, colors: np.ndarray, K: np.ndarray, size: tuple[int, int], radius: int = 1) -> np.ndarray:
    """Z-buffered point splatting of camera-frame points (N, 3) into an (H, W, 3) float image."""
    H, W = size
    img = np.ones((H, W, 3))
    zbuf = np.full((H, W), np.inf)
    z = points[:, 2]
    ok = z > 0.05
    u = np.round(K[0, 0] * points[ok, 0] / z[ok] + K[0, 2]).astype(int)
    v = np.round(K[1, 1] * points[ok, 1] / z[ok] + K[1, 2]).astype(int)
    zz, cc = z[ok], colors[ok]
    order = np.argsort(-zz)  # far first, near overwrite
    for du in range(-radius, radius + 1):
        for dv in range(-radius, radius + 1):
            uu, vv = u[order] + du, v[order] + dv
            m = (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
            img[vv[m], uu[m]] = cc[order][m]
            zbuf[vv[m], uu[m]] = np.minimum(zbuf[vv[m], uu[m]], zz[order][m])
    return img


def top_view(points: np.ndarray, colors: np.ndarray, ax) -> None:
    """Scatter of the points seen from above the fragment (fragment frame: y is down)."""
    order = np.argsort(-points[:, 1])  # high points (small y) drawn last
    ax.scatter(points[order, 0], points[order, 2], c=np.clip(colors[order], 0, 1), s=0.5, linewidths=0)
    ax.set_aspect("equal")
    no_ticks(ax)


def dataset_figure(root: str | Path, scene: str | None = None, out: str | Path = "dataset.png") -> Path:
    plt = pyplot()
    layout = Layout(root)
    if scene is None:
        scene = layout.scenes("test")[0]
    n = layout.n_fragments(scene)
    frags = [0, min(1, n - 1)]
    fig, axes = plt.subplots(3, 4, figsize=(16, 10))
    for col, i in enumerate(frags):
        info = read_fragment_info(layout.fragment_info(scene, i))
        cpath, dpath, _ = frame_paths(layout.frame_prefix(scene, info.seq, info.first_frame))
        color, depth = read_color(cpath), read_depth(dpath)
        axes[0, 2 * col].imshow(color)
        axes[0, 2 * col].set_title(f"{scene} frame {info.first_frame} color")
        im = axes[0, 2 * col + 1].imshow(np.where(depth > 0, depth, np.nan), cmap="turbo")
        axes[0, 2 * col + 1].set_title(f"depth (m), {100 * (depth == 0).mean():.1f}% holes")
        fig.colorbar(im, ax=axes[0, 2 * col + 1], fraction=0.035)
        pts, cols = read_cloud(layout.fragment(scene, i))
        cols = cols if cols is not None else np.full_like(pts, 0.5)
        from pcrcg.data.layout import read_intrinsics

        K = read_intrinsics(layout.intrinsics(scene))
        axes[1, 2 * col].imshow(splat(pts, cols, K, depth.shape))
        axes[1, 2 * col].set_title(f"cloud_bin_{i} ({len(pts)} pts) from its first camera")
        top_view(pts, cols, axes[1, 2 * col + 1])
        axes[1, 2 * col + 1].set_title(f"cloud_bin_{i} from above")
    # aligned pairs of both benchmarks
    from pcrcg.data.layout import read_gt_log, read_gt_overlap

    for col, bench in enumerate(("3DMatch", "3DLoMatch")):
        d = layout.benchmark_dir(bench, scene)
        recs = read_gt_log(d / "gt.log", scene) if (d / "gt.log").is_file() else []
        ax_a, ax_b = axes[2, 2 * col], axes[2, 2 * col + 1]
        if not recs:
            ax_a.set_title(f"{bench}: no pair in {scene}")
            ax_a.axis("off")
            ax_b.axis("off")
            continue
        ov = read_gt_overlap(d / "gt_overlap.log")
        r = recs[0]
        pi, _ = read_cloud(layout.fragment(scene, r.i))
        pj, _ = read_cloud(layout.fragment(scene, r.j))
        pj_in_i = transform_points(r.transform, pj)
        for ax, view in ((ax_a, "xz"), (ax_b, "xy")):
            a, b = (0, 2) if view == "xz" else (0, 1)
            ax.scatter(pi[:, a], pi[:, b], s=0.3, c="tab:orange", linewidths=0, alpha=0.6)
            ax.scatter(pj_in_i[:, a], pj_in_i[:, b], s=0.3, c="tab:blue", linewidths=0, alpha=0.6)
            ax.set_aspect("equal")
            no_ticks(ax)
        ax_a.set_title(f"{bench} pair {r.i}-{r.j}, overlap {ov.get((r.i, r.j), float('nan')):.2f} (top)")
        ax_b.set_title("same pair, front")
    for ax in axes[0].tolist() + [axes[1, 0], axes[1, 2]]:
        no_ticks(ax)
    fig.tight_layout()
    return save_figure(fig, out, dpi=80)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("root")
    ap.add_argument("--scene")
    ap.add_argument("--out", default="dataset.png")
    a = ap.parse_args()
    print(dataset_figure(a.root, a.scene, a.out))


if __name__ == "__main__":
    main()
