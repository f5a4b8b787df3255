"""Match quality of the 2D matchers (sift, orb, lightglue) on real frames and on generated views.

``python -m pcrcg.benchmarks.matching [--pairs 8] [--methods sift,orb,lightglue[:key=value...]] [--real DIR]
[--root DIR] [--sizes 320x240,160x120] [--gap 40] [--threads 1] [--skip real,generated]
[--pair-modes paper,covisible]``

Prints two tables (asserts nothing):

* **real frames** (``--real``, default ``../shared/data/real-rgbd/7-scenes-redkitchen/seq-01``, its
  ``camera-intrinsics.txt`` one folder up; skipped when absent): frame pairs ``(i, i + gap)`` (the first
  is 8 / 47) whose two-way depth overlap is at least 0.3, resized to each ``--sizes`` (H x W; depth by
  nearest neighbour, intrinsics scaled): verified matches per pair, **precision** (the share of the
  matches with depth at ``uv_a`` whose reprojection through that depth and the frames' poses lands
  within 3 px of ``uv_b``) and the median error, twice: with ``camera-intrinsics.txt`` for color and
  depth (as 3DMatch uses the frames), and with the color pixels mapped to the depth camera's as a camera
  of focal ``--color-focal`` (525 px at 640x480, the Kinect v1 RGB camera's nominal value: 7-Scenes'
  intrinsics are the depth camera's 585 px, and its color and depth are not registered, so the first
  precision mostly measures that ~10% scale); then a depth-free precision, through the poses alone at
  that color focal: the share of matches within 3 px of their epipolar lines in both images (``epi@3px``),
  and SuperGlue's ScanNet criterion (``epi SG``: squared symmetric epipolar distance in normalised
  coordinates below 5e-4, ~6 px at 320x240), with the median distance. The depth criteria are bounded by
  7-Scenes' ground truth (depth and color neither registered nor synchronised: SIFT's verified matches
  score ~0.7 there too); the epipolar ones cannot see a match that is wrong along its line (shuffled
  matches score ~0.06 / 0.08). Seconds per image (keypoints) and per pair (matching + verification).
* **generated views** (``--root``, default ``data/synthmatch-cpu`` once its ``manifest.json`` exists,
  else ``data/synthmatch-tiny``; skipped when absent): the 3DMatch and 3DLoMatch pairs (``--pairs``
  per benchmark, evenly spread), 3 views per fragment, the view pairs of ``matcher2d.pairs``, matched
  as a run of the profile matches them (at ``profile.lifting.match_image_size``: cpu, the views' 200x150;
  the matches land on the projection grid ``profile.lifting.image_size``): matches per view pair,
  precision (3 px of the grid, through the ground-truth pose), and explicit color coverage at windows
  3/7/11/17 (2 views) and views 1/2/3 (11x11) from :func:`pcrcg.lifting.coverage.coverage_sweep`
  (implicit coverage beside it for reference). ``--pair-modes paper,covisible`` adds rows with the
  view pairs that see each other most (ranked through the ground-truth pose: an oracle).

Matcher settings are those of ``conf/matcher2d/<method>.yaml``; timings use ``--threads`` (default 1:
shared machines). Nothing is cached between runs (a fresh temporary match cache per invocation).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

# the reprojection residual (K, 2) of matches has one home, shared with matcher2d.oracle_px
from pcrcg.vision.matching import reprojection_residuals as match_residuals

REPO = Path(__file__).resolve().parents[2]
REAL_DEFAULT = REPO.parent / "shared" / "data" / "real-rgbd" / "7-scenes-redkitchen" / "seq-01"
PRECISION_PX = 3.0
MAX_DEPTH = 10.0  # metres; 7-Scenes marks missing depth with 65535 mm
# The Kinect v1's RGB camera: focal length 525 px at 640x480 (its nominal value; 7-Scenes' and 3DMatch's
# camera-intrinsics.txt hold the depth camera's 585 px, which 7-Scenes' color frames do not share)
KINECT_RGB_FOCAL = 525.0


# --------------------------------------------------------------------------- pure functions


def match_errors(*args: Any) -> np.ndarray:
    """``|match_residuals(...)|`` (K,) pixels, NaN without depth."""
    return np.linalg.norm(match_residuals(*args), axis=1)


def precision(residuals: Sequence[np.ndarray], px: float = PRECISION_PX) -> dict[str, float]:
    """Over view pairs' residuals (K, 2): ``precision`` (share of the matches with depth within ``px``),
    ``with_depth``, ``median_px``, and ``precision_debiased``: the same after subtracting each view
    pair's median residual (a diagnostic for ground truth whose depth, color and poses disagree by a
    shift, as 7-Scenes' unregistered, unsynchronised Kinect frames do; ~0 change on exact ground truth)."""
    ok = [np.asarray(r, np.float64)[np.isfinite(np.asarray(r, np.float64)).all(1)] for r in residuals]
    ok = [r for r in ok if len(r)]
    if not ok:
        return {"precision": float("nan"), "with_depth": 0, "median_px": float("nan"), "precision_debiased": float("nan")}
    e = np.concatenate([np.linalg.norm(r, axis=1) for r in ok])
    d = np.concatenate([np.linalg.norm(r - np.median(r, axis=0), axis=1) for r in ok])
    return {"precision": float((e < px).mean()), "with_depth": int(len(e)), "median_px": float(np.median(e)),
            "precision_debiased": float((d < px).mean())}


def epipolar_distances(uv_a: np.ndarray, uv_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                       T_b_a: np.ndarray) -> np.ndarray:
    """Point-to-epipolar-line distances (K, 2) of matches uv_a (K, 2) -> uv_b (K, 2) under the relative
    pose ``T_b_a`` (4x4, camera a -> camera b) and intrinsics ``K_a`` / ``K_b`` (3, 3): column 0 is the
    distance (pixels of b) of ``uv_b`` to the epipolar line of ``uv_a``, column 1 that (pixels of a) of
    ``uv_a`` to the line of ``uv_b``. Depth-free: a match can be wrong along its line and still score 0.
    NaN rows for a degenerate line (no translation, or the epipole itself)."""
    R, t = np.asarray(T_b_a, np.float64)[:3, :3], np.asarray(T_b_a, np.float64)[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    F = np.linalg.inv(np.asarray(K_b, np.float64)).T @ tx @ R @ np.linalg.inv(np.asarray(K_a, np.float64))
    xa = np.c_[np.asarray(uv_a, np.float64).reshape(-1, 2), np.ones(len(uv_a))]
    xb = np.c_[np.asarray(uv_b, np.float64).reshape(-1, 2), np.ones(len(uv_b))]
    line_b, line_a = xa @ F.T, xb @ F  # (K, 3): lines in b (of uv_a) and in a (of uv_b)
    alg = np.abs(np.sum(xb * line_b, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.stack([alg / np.hypot(line_b[:, 0], line_b[:, 1]), alg / np.hypot(line_a[:, 0], line_a[:, 1])], 1)
    return np.where(np.isfinite(d), d, np.nan)


# SuperGlue's ScanNet criterion (Sarlin et al. 2020, kept by LightGlue's indoor evaluations): a match is
# correct when its squared symmetric epipolar distance in normalised image coordinates is below 5e-4
SUPERGLUE_EPI_THRESHOLD = 5e-4


def epipolar_precision(distances: Sequence[np.ndarray], focal: float, px: float = PRECISION_PX) -> dict[str, float]:
    """Over view pairs' :func:`epipolar_distances` (K, 2) of cameras of focal ``focal`` (pixels):
    ``precision_epi`` (share of matches with both distances within ``px``), ``precision_sg`` (share
    meeting :data:`SUPERGLUE_EPI_THRESHOLD`: ``(d_b / f)^2 + (d_a / f)^2 < 5e-4``) and ``median_epi_px``
    (median of the larger distance)."""
    d = [np.asarray(x, np.float64).reshape(-1, 2) for x in distances]
    d = [x[np.isfinite(x).all(1)] for x in d]
    d = np.concatenate(d) if any(len(x) for x in d) else np.zeros((0, 2))
    if not len(d):
        return {"precision_epi": float("nan"), "precision_sg": float("nan"), "median_epi_px": float("nan")}
    return {"precision_epi": float((d.max(1) < px).mean()),
            "precision_sg": float((((d / focal) ** 2).sum(1) < SUPERGLUE_EPI_THRESHOLD).mean()),
            "median_epi_px": float(np.median(d.max(1)))}


AS_RUN = "as_run"  # matcher_config: the image_size a run of the profile matches at


def matcher_config(method: str, image_size: Sequence[int] | None | str, profile: str = "cpu") -> Any:
    """``conf/matcher2d/<method>.yaml`` (composed as a run composes it) with ``image_size`` set (``AS_RUN``:
    left as the profile composes it, ``profile.lifting.match_image_size``). ``method`` may carry settings
    of its group after colons, ``lightglue:filter_threshold=0.5:min_matches=20`` (``matcher2d.<key>=<value>``
    each), to compare variants of one matcher in one table; an ``image_size`` among them wins over the
    argument (``lightglue:image_size=null``: native size)."""
    from pcrcg.config import load_run_config
    from pcrcg.vision.matching import MatcherConfig

    name, *settings = method.split(":")
    overrides = [f"matcher2d.{kv.strip()}" for kv in settings if kv.strip()]
    cfg = load_run_config([f"matcher2d={name}", f"profile={profile}", *overrides], validate=False)
    m = MatcherConfig.from_cfg(cfg.matcher2d)
    if image_size == AS_RUN or any(kv.split("=", 1)[0].strip() == "image_size" for kv in settings):
        return m
    return replace(m, image_size=tuple(image_size) if image_size else None)


@dataclass
class Timed:
    """Keypoints and matches of a set of images and view pairs, with their timings."""

    features: dict[Any, Any] = field(default_factory=dict)
    matches: dict[Any, Any] = field(default_factory=dict)
    s_images: float = 0.0
    s_pairs: float = 0.0

    @property
    def s_per_image(self) -> float:
        return self.s_images / max(1, len(self.features))

    @property
    def s_per_pair(self) -> float:
        return self.s_pairs / max(1, len(self.matches))


def timed_matching(images: dict[Any, np.ndarray], pairs: Sequence[tuple[Any, Any]], cfg: Any) -> Timed:
    """:func:`detect_features` on every image (in one call: batched where the method batches), then
    :func:`match_features` per pair; wall-clock seconds of each part."""
    from pcrcg.vision.matching import detect_features, match_features

    keys = list(images)
    t = Timed()
    if keys:
        f0 = detect_features([images[keys[0]]], cfg)[0]  # warm-up: weights load, allocator
        match_features(f0, f0, cfg)
        t0 = time.perf_counter()
        t.features = dict(zip(keys, detect_features([images[k] for k in keys], cfg)))
        t.s_images = time.perf_counter() - t0
    for a, b in pairs:
        t0 = time.perf_counter()
        t.matches[(a, b)] = match_features(t.features[a], t.features[b], cfg)
        t.s_pairs += time.perf_counter() - t0
    return t


# --------------------------------------------------------------------------- real frames


@dataclass
class Frame:
    color: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    pose: np.ndarray  # camera-to-world


def read_frame(folder: Path, fid: int, K: np.ndarray, size: Sequence[int] | None = None) -> Frame:
    """One RGB-D frame ``frame-XXXXXX.color.(jpg|png)`` / ``.depth.png`` / ``.pose.txt``, at ``size``."""
    from pcrcg.data.layout import read_color, read_depth, read_pose
    from pcrcg.errors import DataError
    from pcrcg.vision.pretrain import resize_view

    stem = folder / f"frame-{fid:06d}"
    color_path = next((p for p in (stem.with_suffix(".color.jpg"), stem.with_suffix(".color.png")) if p.is_file()), None)
    if color_path is None:
        raise DataError(stem.with_suffix(".color.jpg"), "missing (nor .color.png)")
    color = read_color(color_path)
    depth = read_depth(stem.with_suffix(".depth.png"))
    depth[depth > MAX_DEPTH] = 0.0
    pose = read_pose(stem.with_suffix(".pose.txt"))
    c, d, K2 = resize_view(color, depth, K, size)
    return Frame(c, d, K2, pose)


def real_pairs(folder: Path, K: np.ndarray, n: int, gap: int = 40, min_overlap: float = 0.3) -> list[tuple[int, int]]:
    """Up to ``n`` frame pairs ``(i, j)``: (8, 47) first, then ``(i, i + gap)`` evenly spread over the
    sequence, kept when both directions' depth overlap is at least ``min_overlap``."""
    from pcrcg.vision.pretrain import overlap_ratio, relative_pose

    ids = sorted(int(p.name[6:12]) for p in folder.glob("frame-*.pose.txt"))
    if len(ids) < 2:
        return []
    have = set(ids)
    cand = [(8, 47)] + [(i, i + gap) for i in np.linspace(ids[0], ids[-1] - gap, max(4 * n, 8)).round().astype(int)]
    out: list[tuple[int, int]] = []
    for i, j in cand:
        if len(out) >= n:
            break
        if i not in have or j not in have or (i, j) in out:
            continue
        fa, fb = read_frame(folder, i, K, (120, 160)), read_frame(folder, j, K, (120, 160))
        T = relative_pose(fa.pose, fb.pose)
        ov = min(overlap_ratio(fa.depth, fa.K, fb.depth, fb.K, T, stride=4),
                 overlap_ratio(fb.depth, fb.K, fa.depth, fa.K, np.linalg.inv(T), stride=4))
        if ov >= min_overlap:
            out.append((int(i), int(j)))
    return out


def rgb_to_depth_pixels(uv: np.ndarray, K_depth: np.ndarray, f_color: float) -> np.ndarray:
    """Color pixels (K, 2) of a camera with focal ``f_color`` (same principal point) -> the depth camera's
    pixels (``K_depth``): a scale about the principal point (the two cameras' baseline is ignored)."""
    c = np.array([K_depth[0, 2], K_depth[1, 2]])
    return c + (np.asarray(uv, np.float64) - c) * (K_depth[0, 0] / f_color)


def bench_real(folder: Path, methods: Sequence[str], sizes: Sequence[tuple[int, int]], n_pairs: int,
               gap: int, color_focal: float = KINECT_RGB_FOCAL) -> tuple[list[dict], str]:
    from pcrcg.data.layout import read_intrinsics
    from pcrcg.vision.pretrain import relative_pose

    K = read_intrinsics(folder.parent / "camera-intrinsics.txt")
    pairs = real_pairs(folder, K, n_pairs, gap)
    rows = []
    for size in sizes:
        ids = sorted({i for p in pairs for i in p})
        frames = {i: read_frame(folder, i, K, size) for i in ids}
        for method in methods:
            cfg = matcher_config(method, None)
            t = timed_matching({i: frames[i].color for i in ids}, pairs, cfg)
            errs, errs_rgb, epi = [], [], []
            f_rgb = color_focal * size[1] / 640.0
            for (i, j), m in t.matches.items():
                fa, fb = frames[i], frames[j]
                T = relative_pose(fa.pose, fb.pose)
                errs.append(match_residuals(m.uv_a, m.uv_b, fa.depth, fa.K, fb.K, T))
                errs_rgb.append(match_residuals(rgb_to_depth_pixels(m.uv_a, fa.K, f_rgb),
                                                rgb_to_depth_pixels(m.uv_b, fb.K, f_rgb), fa.depth, fa.K, fb.K, T))
                K_rgb = np.array([[f_rgb, 0.0, fa.K[0, 2]], [0.0, f_rgb, fa.K[1, 2]], [0.0, 0.0, 1.0]])
                epi.append(epipolar_distances(m.uv_a, m.uv_b, K_rgb, K_rgb, T))
            counts = [len(m) for m in t.matches.values()]
            rgb = {f"{k}_rgb": v for k, v in precision(errs_rgb).items()}
            rows.append({"size": f"{size[1]}x{size[0]}", "method": method, "pairs": len(pairs),
                         "keypoints": float(np.mean([len(f) for f in t.features.values()])),
                         "matches": float(np.mean(counts)) if counts else 0.0, **precision(errs), **rgb,
                         **epipolar_precision(epi, f_rgb),
                         "s_image": t.s_per_image, "s_pair": t.s_per_pair})
    title = (f"real frames: {folder} ({len(pairs)} pairs: {', '.join(f'{i}/{j}' for i, j in pairs)}; "
             f"two-way depth overlap >= 0.3); precision with the intrinsics file for color and depth, and with "
             f"color at the Kinect RGB camera's focal {color_focal:g} px (640x480)")
    return rows, title


# --------------------------------------------------------------------------- generated views


def default_root() -> Path:
    cpu = REPO / "data" / "synthmatch-cpu"
    return cpu if (cpu / "manifest.json").is_file() else REPO / "data" / "synthmatch-tiny"


def bench_generated(root: Path, methods: Sequence[str], n_pairs: int, benchmarks: Sequence[str] = ("3DMatch", "3DLoMatch"),
                    depth_tolerance: float = 0.1, profile: str = "cpu",
                    pair_modes: Sequence[str] = ("paper",)) -> tuple[list[dict], str]:
    from pcrcg.config import profile_node
    from pcrcg.lifting.coverage import coverage_sweep, load_samples
    from pcrcg.vision.matching import MatchCache, matched_view_pairs

    lifting = profile_node(profile).lifting
    grid = tuple(lifting.image_size)
    rows = []
    with tempfile.TemporaryDirectory(prefix="pcrcg-matchbench-") as tmp:
        for bench in benchmarks:
            samples = load_samples(str(root), bench, n_pairs, n_views=3)
            for method, mode in [(m, pm) for pm in pair_modes for m in methods]:
                cfg = replace(matcher_config(method, AS_RUN, profile), pairs=mode)
                label = method if mode == "paper" else f"{method}/{mode}"
                cache = MatchCache(Path(tmp) / f"{bench}-{method}-{mode}")
                images, todo = {}, []
                for k, s in enumerate(samples):
                    for a, b in matched_view_pairs(s.src_views, s.tgt_views, cfg, s.transform):
                        images[(k, "s", a)] = s.src_views[a].color
                        images[(k, "t", b)] = s.tgt_views[b].color
                        todo.append(((k, "s", a), (k, "t", b)))
                t = timed_matching(images, todo, cfg)
                errs = []
                for (sa, tb), m in t.matches.items():
                    s = samples[sa[0]]
                    va, vb = s.src_views[sa[2]], s.tgt_views[tb[2]]
                    key, material = cache.key(va.color, vb.color, cfg, va.color_path, vb.color_path)
                    cache.save(key, m, material)  # coverage_sweep reads these
                    T_b_a = np.linalg.inv(vb.pose) @ s.transform @ va.pose
                    scale = grid[1] / va.color.shape[1]  # input pixels -> grid pixels
                    errs.append(scale * match_residuals(m.uv_a, m.uv_b, va.depth, va.intrinsics, vb.intrinsics, T_b_a))
                cov = coverage_sweep(samples, depth_tolerance=depth_tolerance, image_size=grid, matcher=cfg, cache=cache)
                counts = [len(m) for m in t.matches.values()]
                row = {"benchmark": bench, "method": label, "pairs": len(samples), "view_pairs": len(counts),
                       "matches": float(np.mean(counts)) if counts else 0.0, **precision(errs),
                       "s_image": t.s_per_image, "s_pair": t.s_per_pair}
                for r in cov:
                    tag = f"{'exp' if r.projection == 'explicit' else 'imp'}_v{r.views}" + (
                        f"_w{r.window_size}" if r.projection == "explicit" else "")
                    row[tag] = r.color_coverage
                rows.append(row)
    match = lifting.match_image_size
    at = "native size" if match is None else f"{match[1]}x{match[0]}"
    title = (f"generated views: {root} (3 views per fragment, view pairs {'/'.join(pair_modes)}, matched at "
             f"{at} as a {profile} run unless a method sets image_size, onto the {grid[1]}x{grid[0]} grid; "
             f"coverage = share of both fragments' points lifted, depth tolerance {depth_tolerance} m)")
    return rows, title


# --------------------------------------------------------------------------- printing


def _f(v: Any, spec: str) -> str:
    if isinstance(v, float) and not np.isfinite(v):
        return "-"
    return format(v, spec)


def format_real(rows: Sequence[dict]) -> str:
    head = (f"{'size':>8} {'method':<10} {'keypts':>7} {'matches/pair':>12} {'prec@3px':>8} {'med px':>6} "
            f"{'prec@3px RGB-f':>14} {'med px':>6} {'epi@3px':>7} {'epi SG':>6} {'med px':>6} {'s/image':>8} {'s/pair':>8}")
    lines = [head]
    for r in rows:
        lines.append(f"{r['size']:>8} {r['method']:<10} {_f(r['keypoints'], '7.0f')} {_f(r['matches'], '12.1f')} "
                     f"{_f(r['precision'], '8.3f')} {_f(r['median_px'], '6.2f')} {_f(r['precision_rgb'], '14.3f')} "
                     f"{_f(r['median_px_rgb'], '6.2f')} {_f(r['precision_epi'], '7.3f')} {_f(r['precision_sg'], '6.3f')} "
                     f"{_f(r['median_epi_px'], '6.2f')} {_f(r['s_image'], '8.3f')} {_f(r['s_pair'], '8.3f')}")
    return "\n".join(lines)


def format_generated(rows: Sequence[dict]) -> str:
    wins = (3, 7, 11, 17)
    head = (f"{'benchmark':<10} {'method':<20} {'pairs':>5} {'matches/vp':>10} {'prec@3px':>8} {'med px':>6} {'s/image':>8} "
            f"{'s/pair':>7} | explicit, 2 views: " + " ".join(f"{f'w{w}':>6}" for w in wins)
            + " | explicit 11x11: " + " ".join(f"{f'v{v}':>6}" for v in (1, 2, 3))
            + " | implicit: " + " ".join(f"{f'v{v}':>6}" for v in (1, 2, 3)))
    lines = [head]
    for r in rows:
        cov_w = " ".join(f"{100 * r.get(f'exp_v2_w{w}', float('nan')):5.1f}%" for w in wins)
        cov_v = " ".join(f"{100 * r.get(f'exp_v{v}_w11', float('nan')):5.1f}%" for v in (1, 2, 3))
        cov_i = " ".join(f"{100 * r.get(f'imp_v{v}', float('nan')):5.1f}%" for v in (1, 2, 3))
        lines.append(f"{r['benchmark']:<10} {r['method']:<20} {r['pairs']:>5} {_f(r['matches'], '10.1f')} "
                     f"{_f(r['precision'], '8.3f')} {_f(r['median_px'], '6.2f')} {_f(r['s_image'], '8.3f')} {_f(r['s_pair'], '7.3f')} "
                     f"|                    {cov_w} |                 {cov_v} |           {cov_i}")
    return "\n".join(lines)


def _size(text: str) -> tuple[int, int]:
    w, h = (int(x) for x in text.lower().split("x"))
    return h, w


def main(argv: Sequence[str] | None = None) -> dict[str, list[dict]]:
    import cv2
    import torch

    ap = argparse.ArgumentParser(prog="python -m pcrcg.benchmarks.matching", description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=8, help="pairs per set (real frames; each generated benchmark)")
    ap.add_argument("--methods", default="sift,orb,lightglue",
                    help="matchers, each optionally with settings: lightglue:filter_threshold=0.5:ransac_threshold=1")
    ap.add_argument("--real", default=str(REAL_DEFAULT), help="a folder of real RGB-D frames (3DMatch layout)")
    ap.add_argument("--root", default=None, help="a generated data root (default: synthmatch-cpu, else -tiny)")
    ap.add_argument("--sizes", default="320x240,160x120", help="W x H the real frames are matched at")
    ap.add_argument("--gap", type=int, default=40, help="frame gap of the real pairs")
    ap.add_argument("--color-focal", type=float, default=KINECT_RGB_FOCAL,
                    help="focal length (px at 640x480) of the real frames' color camera for the second precision")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--skip", default="", help="real and/or generated")
    ap.add_argument("--pair-modes", default="paper", help="matcher2d.pairs for the generated views: paper,all,covisible")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    print(f"pcrcg.benchmarks.matching: torch {torch.__version__}, {args.threads} thread(s), "
          f"device for learned networks: {'cuda' if torch.cuda.is_available() else 'cpu'}")
    out: dict[str, list[dict]] = {"real": [], "generated": []}
    real = Path(args.real)
    if "real" in skip:
        pass
    elif not (real.is_dir() and (real.parent / "camera-intrinsics.txt").is_file()):
        print(f"real frames: {real} is absent (or has no ../camera-intrinsics.txt): skipped")
    else:
        rows, title = bench_real(real, methods, [_size(s) for s in args.sizes.split(",")], args.pairs, args.gap,
                                 args.color_focal)
        print(title)
        print(format_real(rows))
        out["real"] = rows
    root = Path(args.root) if args.root else default_root()
    if "generated" in skip:
        pass
    elif not (root / "manifest.json").is_file():
        print(f"generated views: {root} is absent (no manifest.json; python -m pcrcg.prepare makes it): skipped")
    else:
        rows, title = bench_generated(root, methods, args.pairs,
                                      pair_modes=[p.strip() for p in args.pair_modes.split(",") if p.strip()])
        print(title)
        print(format_generated(rows))
        out["generated"] = rows
    return out


if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.benchmarks.matching"):  # a bad file or setting: one line, exit 2
        main()
