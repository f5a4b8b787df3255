"""Speed of the 2D branch and the projection module (prints figures; asserts nothing).

``python -m pcrcg.benchmarks.vision [threads=1] [reps=3] [archs=[resnet18,resnet34,resnet50]]
[sizes=[[120,160],[240,320]]] [points=[2000,10000,30000,100000]] [skip=[]]``

* matcher: seconds per image pair (SIFT and ORB, full pipeline incl. F-RANSAC) at 160x120,
  320x240, 640x480 on toy-room renders;
* lifting: seconds per pair (both fragments, 2 views each) against the number of points per
  fragment, implicit and explicit, rgb features and 32-wide deep maps (forward + backward through
  the gather, encoder excluded);
* encoder: seconds per pair for forward + backward of the ResUNet (4 images: 2 views x 2
  fragments) per arch and encoder input size.

``skip=[matcher]`` etc. leaves a part out. Threads default to 1 (shared machines).
"""

from __future__ import annotations

import time
from typing import Any, Callable, Sequence

import numpy as np


def _time(fn: Callable[[], Any], reps: int) -> float:
    fn()  # warm-up
    t = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return float(np.median(t))


def bench_matcher(reps: int = 3, sizes: Sequence[tuple[int, int]] = ((120, 160), (240, 320), (480, 640))) -> list[dict]:
    from pcrcg.testing.scenes import make_pair
    from pcrcg.vision.matching import MatcherConfig, match_images

    rows = []
    for h, w in sizes:
        s = make_pair(0, width=w, height=h, frames=3, voxel=0.1)
        a, b = s.src_views[0].color, s.tgt_views[0].color
        for method in ("sift", "orb"):
            cfg = MatcherConfig(method=method)
            n = len(match_images(a, b, cfg))
            sec = _time(lambda: match_images(a, b, cfg), reps)
            rows.append({"part": "matcher", "method": method, "image": f"{w}x{h}", "matches": n, "s_per_pair": sec})
    return rows


def _grow(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points resampled from a fragment (with 5 mm jitter when n exceeds its size)."""
    idx = rng.integers(0, len(points), n)
    return (points[idx] + rng.normal(0, 0.005, (n, 3))).astype(np.float32)


def bench_lifting(reps: int = 3, points: Sequence[int] = (2000, 10000, 30000, 100000)) -> list[dict]:
    import torch

    from pcrcg.lifting import ColorLifter, LiftingConfig, lift_pair
    from pcrcg.lifting.projection import keypoints_per_view
    from pcrcg.testing.scenes import make_pair
    from pcrcg.vision.matching import MatcherConfig, match_views

    base = make_pair(0)
    matches = match_views(base.src_views[:2], base.tgt_views[:2], MatcherConfig())
    rng = np.random.default_rng(0)
    rows = []
    for n in points:
        s = base.__class__(**{**base.__dict__, "src_points": _grow(base.src_points, n, rng),
                              "tgt_points": _grow(base.tgt_points, n, rng)})
        for proj in ("implicit", "explicit"):
            lifter = ColorLifter(LiftingConfig(proj, "rgb", views=2, window_size=11))
            sec = _time(lambda: lift_pair(lifter, s, matches), reps)
            rows.append({"part": "lifting", "projection": proj, "features": "rgb", "points": n, "s_per_pair": sec})
            # deep: 32-wide maps with gradients, forward + backward through the gather
            lifter = ColorLifter(LiftingConfig(proj, "sift", views=2, window_size=11, feature_dim=32))
            skp, tkp = keypoints_per_view(matches, 2, 2) if proj == "explicit" else (None, None)
            ps, pt = torch.from_numpy(s.src_points), torch.from_numpy(s.tgt_points)

            maps = torch.randn(4, 32, 120, 160, requires_grad=True)  # stands in for the encoder output

            def step() -> None:
                maps.grad = None
                fs, _ = lifter(ps, s.src_views, skp, list(maps[:2]))
                ft, _ = lifter(pt, s.tgt_views, tkp, list(maps[2:]))
                (fs.sum() + ft.sum()).backward()

            sec = _time(step, reps)
            rows.append({"part": "lifting", "projection": proj, "features": "deep32+bwd", "points": n, "s_per_pair": sec})
    return rows


def bench_encoder(reps: int = 2, archs: Sequence[str] = ("resnet18", "resnet34", "resnet50"),
                  sizes: Sequence[tuple[int, int]] = ((120, 160), (240, 320)), out_dim: int = 32) -> list[dict]:
    import torch

    from pcrcg.vision.encoders import ResUNet

    rows = []
    for arch in archs:
        model = ResUNet(arch, out_dim)
        model.train()
        for h, w in sizes:
            x = torch.rand(4, 3, h, w)

            def step() -> None:
                model.zero_grad(set_to_none=True)
                model(x).square().mean().backward()

            sec = _time(step, reps)
            n_par = sum(p.numel() for p in model.parameters()) / 1e6
            rows.append({"part": "encoder", "arch": arch, "image": f"{w}x{h}", "batch": 4, "params_M": round(n_par, 1),
                         "s_per_pair": sec})
    return rows


def _print(rows: list[dict]) -> None:
    for r in rows:
        print("  " + "  ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items() if k != "part"))


def main(argv: Sequence[str] | None = None) -> list[dict]:
    import sys

    import cv2
    import torch
    from omegaconf import OmegaConf

    args = OmegaConf.from_dotlist(list(sys.argv[1:] if argv is None else argv))
    threads = int(args.get("threads", 1))
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    reps = int(args.get("reps", 3))
    skip = set(args.get("skip", []))
    print(f"pcrcg.benchmarks.vision: torch {torch.__version__}, {threads} thread(s), median of {reps}")
    rows: list[dict] = []
    if "matcher" not in skip:
        print("matcher (seconds per image pair):")
        r = bench_matcher(reps)
        _print(r)
        rows += r
    if "lifting" not in skip:
        print("lifting (seconds per pair, 2 views per fragment, N points per fragment):")
        r = bench_lifting(reps, [int(x) for x in args.get("points", [2000, 10000, 30000, 100000])])
        _print(r)
        rows += r
    if "encoder" not in skip:
        print("encoder forward+backward (seconds per pair = 4 images):")
        sizes = [tuple(int(v) for v in s) for s in args.get("sizes", [[120, 160], [240, 320]])]
        r = bench_encoder(max(1, reps - 1), list(args.get("archs", ["resnet18", "resnet34", "resnet50"])), sizes)
        _print(r)
        rows += r
    return rows


if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.benchmarks.vision"):  # a bad file or setting: one line, exit 2
        main()
