"""Color coverage over a view sweep (1, 2, 3) and an explicit window sweep (3, 7, 11, 17).

``python -m pcrcg.lifting.coverage data.root=data/synthmatch-tiny split=val n_pairs=8``
prints one row per setting and whether coverage grows as the paper says (views 1 < 2 <= 3,
windows 3 < 7 < 11 < 17). Without ``data.root`` it runs on toy pairs (:mod:`pcrcg.testing.scenes`).
Other keys: ``views=[1,2,3] windows=[3,7,11,17] base_views=2 base_window=11
depth_tolerance=0.1 image_size=null window_style=centred|official method=sift|orb|lightglue pairs=paper|all|covisible
cache_dir=cache/matches`` (``window_style`` centred by default here, as the README's figures; a run's default is official).
Coverage depends only on geometry and matches, so no feature map is computed.

Where the pairs carry their ground-truth pose (a benchmark's or a split's pairs: ``split=3DLoMatch``), each row
also says how the *overlap* is colored: of the source points within ``overlap_radius`` (m, default 0.0375:
Predator's 1.5 x 2.5 cm) of the target after the pose, the share colored in both fragments (the same surface
gets a lifted feature on both sides) and in one fragment only (the same surface enters the 3D network with a
feature on one side and the unseen value on the other). Only the first kind can help matching.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import numpy as np

from pcrcg.geometry import transform_points
from pcrcg.lifting.config import LiftingConfig
from pcrcg.lifting.projection import ColorLifter, color_coverage, pair_covered
from pcrcg.vision.matching import MatchCache, MatcherConfig, match_views


@dataclass
class CoverageRow:
    sweep: str  # "views" or "window"
    projection: str
    views: int
    window_size: int
    color_coverage: float  # mean over pairs
    n_pairs: int
    # of the overlap's source points, mean over the pairs with a pose and an overlap (nan without any):
    overlap_both: float = float("nan")  # colored in both fragments
    overlap_one_side: float = float("nan")  # colored in one fragment only


def overlap_pairs(src_points: np.ndarray, tgt_points: np.ndarray, transform: np.ndarray,
                  radius: float) -> np.ndarray | None:
    """The overlap of a pair: (K, 2) int64 rows (source point, its nearest target point) for the source points
    (N, 3) within ``radius`` of a target point (M, 3) once moved by ``transform`` (4, 4, src -> tgt); None
    when no source point is that close. Depends on the pair only: computed once for every setting."""
    from scipy.spatial import cKDTree

    if len(src_points) == 0 or len(tgt_points) == 0:
        return None
    moved = transform_points(np.asarray(transform, np.float64), np.asarray(src_points, np.float64))
    dist, nn = cKDTree(np.asarray(tgt_points, np.float64)).query(moved, distance_upper_bound=float(radius))
    near = np.flatnonzero(np.isfinite(dist))
    return np.stack([near, nn[near]], axis=1).astype(np.int64) if len(near) else None


def coloring_of(src_covered: np.ndarray, tgt_covered: np.ndarray, pairs: np.ndarray) -> tuple[float, float]:
    """(both, one_side): the share of the overlap ``pairs`` (:func:`overlap_pairs`) colored in both fragments
    and in exactly one. ``src_covered`` (N,) / ``tgt_covered`` (M,) bool."""
    a, b = np.asarray(src_covered, bool)[pairs[:, 0]], np.asarray(tgt_covered, bool)[pairs[:, 1]]
    return float((a & b).mean()), float((a ^ b).mean())


def overlap_coloring(src_covered: np.ndarray, tgt_covered: np.ndarray, src_points: np.ndarray,
                     tgt_points: np.ndarray, transform: np.ndarray, radius: float) -> tuple[float, float] | None:
    """(both, one_side) of one pair (:func:`overlap_pairs`, then :func:`coloring_of`); None without overlap."""
    pairs = overlap_pairs(src_points, tgt_points, transform, radius)
    return None if pairs is None else coloring_of(src_covered, tgt_covered, pairs)


def coverage_sweep(
    samples: Iterable[Any],
    views: Sequence[int] = (1, 2, 3),
    windows: Sequence[int] = (3, 7, 11, 17),
    base_views: int = 2,
    base_window: int = 11,
    depth_tolerance: float = 0.1,
    image_size: Sequence[int] | None = None,
    matcher: MatcherConfig | None = None,
    cache: MatchCache | None = None,
    progress: bool = False,
    overlap_radius: float = 0.0375,
    window_style: str = "centred",
) -> list[CoverageRow]:
    """Mean ``color_coverage`` over ``samples`` (PairSample with >= max(views) views each) for

    * the view sweep, for implicit and explicit (``base_window``) projection;
    * the window sweep, explicit projection with ``base_views`` views.

    The 2D matches of each pair are computed once (all views, ``matcher.pairs``) and reused; with
    ``pairs=covisible`` (which ranks the view pairs of the views in use) once per number of views.
    Samples with a ``transform`` also give :func:`coloring_of` their overlap (:func:`overlap_pairs`, ``overlap_radius`` m,
    found once per pair). ``window_style``: how the explicit windows are drawn (:class:`LiftingConfig`).
    """
    from tqdm import tqdm

    matcher = matcher or MatcherConfig()
    size = tuple(image_size) if image_size else None
    settings: list[tuple[str, str, int, int]] = []
    for proj in ("implicit", "explicit"):
        for v in views:
            settings.append(("views", proj, int(v), int(base_window)))
    for w in windows:
        settings.append(("window", "explicit", int(base_views), int(w)))
    lifters = {s: ColorLifter(LiftingConfig(s[1], "none", s[2], s[3], depth_tolerance, image_size=size,
                                            window_style=window_style)) for s in settings}
    sums = {s: 0.0 for s in settings}
    overlap: dict[tuple[str, str, int, int], list[tuple[float, float]]] = {s: [] for s in settings}
    n = 0
    for sample in tqdm(samples, desc="coverage", disable=not progress):
        nv = max(max(views), base_views)
        T = getattr(sample, "transform", None)
        if matcher.pairs == "covisible":
            by_views = {v: match_views(sample.src_views[:v], sample.tgt_views[:v], matcher, cache, T)
                        for v in sorted({s[2] for s in settings})}
        else:
            every = match_views(sample.src_views[:nv], sample.tgt_views[:nv], matcher, cache, T)
            by_views = {s[2]: every for s in settings}
        pairs = None if T is None else overlap_pairs(np.asarray(sample.src_points), np.asarray(sample.tgt_points),
                                                     T, overlap_radius)
        for s in settings:
            cs, ct = pair_covered(lifters[s], sample, by_views[s[2]])
            sums[s] += color_coverage(cs, ct)
            if pairs is not None:
                overlap[s].append(coloring_of(cs.cpu().numpy(), ct.cpu().numpy(), pairs))
        n += 1
    if n == 0:
        raise ValueError("coverage_sweep: no pairs")
    nan = (float("nan"), float("nan"))
    return [CoverageRow(s[0], s[1], s[2], s[3], sums[s] / n, n,
                        *(tuple(np.mean(overlap[s], axis=0)) if overlap[s] else nan)) for s in settings]


def check_growth(rows: Sequence[CoverageRow]) -> dict[str, bool]:
    """The paper's claims: views 1 < 2 <= 3 (each projection) and windows strictly increasing."""
    out = {}
    for proj in ("implicit", "explicit"):
        c = {r.views: r.color_coverage for r in rows if r.sweep == "views" and r.projection == proj}
        if {1, 2, 3} <= set(c):
            out[f"{proj}: views 1 < 2 <= 3"] = c[1] < c[2] <= c[3]
    w = sorted((r.window_size, r.color_coverage) for r in rows if r.sweep == "window")
    if len(w) > 1:
        out["explicit: windows " + " < ".join(str(x[0]) for x in w)] = all(a[1] < b[1] for a, b in zip(w, w[1:]))
    return out


def format_rows(rows: Sequence[CoverageRow]) -> str:
    lines = [f"{'sweep':<7} {'projection':<9} {'views':>5} {'window':>6} {'color_coverage':>15} "
             f"{'overlap: both':>14} {'one side':>9}"]
    for r in rows:
        win = str(r.window_size) if r.projection == "explicit" else "-"
        lines.append(f"{r.sweep:<7} {r.projection:<9} {r.views:>5} {win:>6} {r.color_coverage:>15.4f} "
                     f"{r.overlap_both:>14.4f} {r.overlap_one_side:>9.4f}")
    lines.append(f"({rows[0].n_pairs} pairs)")
    return "\n".join(lines)


def load_samples(root: str | None, split: str, n_pairs: int, n_views: int = 3, seed: int = 0) -> list[Any]:
    """Up to ``n_pairs`` pairs of a data set (evenly spread), or toy pairs when ``root`` is None."""
    if root is None:
        from pcrcg.testing.scenes import make_pair

        return [make_pair(seed + k) for k in range(n_pairs)]
    from pcrcg.data.dataset import PairDataset

    ds = PairDataset(root, split, n_views=n_views)
    idx = np.unique(np.linspace(0, len(ds) - 1, min(n_pairs, len(ds))).round().astype(int))
    return [ds[int(k)] for k in idx]


def main(argv: Sequence[str] | None = None) -> list[CoverageRow]:
    import sys

    from omegaconf import OmegaConf

    args = OmegaConf.from_dotlist(list(sys.argv[1:] if argv is None else argv))
    root = OmegaConf.select(args, "data.root")
    samples = load_samples(root, str(args.get("split", "val")), int(args.get("n_pairs", 4)))
    mnode = {k: args[k] for k in ("method", "ratio", "mutual", "ransac_threshold", "max_keypoints",
                                  "min_matches", "pairs", "covisible_k") if k in args}
    cache_dir = args.get("cache_dir", "cache/matches" if root else None)
    rows = coverage_sweep(
        samples,
        views=list(args.get("views", [1, 2, 3])),
        windows=list(args.get("windows", [3, 7, 11, 17])),
        base_views=int(args.get("base_views", 2)),
        base_window=int(args.get("base_window", 11)),
        depth_tolerance=float(args.get("depth_tolerance", 0.1)),
        image_size=args.get("image_size", None),
        matcher=MatcherConfig.from_cfg(mnode),
        cache=MatchCache(cache_dir) if cache_dir else None,
        progress=True,
        overlap_radius=float(args.get("overlap_radius", 0.0375)),
        window_style=str(args.get("window_style", "centred")),
    )
    print(f"data: {root or 'toy scene (pcrcg.testing.scenes)'}")
    print(format_rows(rows))
    for claim, ok in check_growth(rows).items():
        print(f"{'OK  ' if ok else 'FAIL'} {claim}")
    return rows


if __name__ == "__main__":
    main()
