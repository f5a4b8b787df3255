"""Measuring one column (a :class:`~pcrcg.data.stats.sources.Source`): fragments, pairs, FPFH, images.

Every function returns plain JSON-ready dicts; None stands for "not measurable here" (a root
without frames has no image rows, a folder without benchmark files no pair rows).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from pcrcg.data.layout import BENCHMARKS, Layout, PairRecord, read_cloud, read_depth, read_gt_info
from pcrcg.data.stats import measures as M
from pcrcg.data.stats.sources import FragmentRef, Source, color_path, depth_path, evenly, read_rgb



@dataclass
class StatsConfig:
    """Settings of every measure (written into the JSON beside the numbers)."""

    count_voxel: float = 0.025  # points per fragment, extent
    extent_trim: float = 2.0  # extent between the 2nd and 98th percentiles
    shape_voxel: float = 0.05  # planarity, normals
    n_planes: int = 4
    plane_distance: float = 0.02
    plane_iterations: int = 1000
    normal_radius: float = 2.0  # x shape_voxel
    normal_max_nn: int = 30
    n_cells: int = 200  # axial Fibonacci cells of the normal-orientation entropy
    seed: int = 0
    fragments: int | None = 100  # fragments measured per column (evenly spread; None/0: all)
    pairs: int | None = 30  # benchmark pairs per benchmark for FPFH and SIFT (None/0: all)
    frames: int | None = 200  # depth frames for the hole rate
    profile: str = "cpu"  # conf/profile/<profile>.yaml: RANSAC iterations (FPFH), lifting.image_size (SIFT)
    fpfh: bool = True
    sift: bool = True
    preview: int = 3  # fragments per column in the picture


# --------------------------------------------------------------------------- fragments


def fragment_measures(points: np.ndarray, cfg: StatsConfig) -> dict[str, Any]:
    """All per-fragment numbers of points (N, 3): ``points`` (count at ``count_voxel``),
    ``extent_pca`` (3, sorted) and ``extent_xyz`` (3), ``planarity``, ``normal_entropy``."""
    p25 = M.voxel_downsample(points, cfg.count_voxel)
    p5 = M.voxel_downsample(points, cfg.shape_voxel)
    return {
        "points": int(len(p25)),
        "extent_pca": M.extent_sides(p25, trim=cfg.extent_trim).tolist(),
        "extent_xyz": M.extent_sides(p25, pca=False, trim=cfg.extent_trim).tolist(),
        "planarity": M.planarity(p5, cfg.n_planes, cfg.plane_distance, voxel=0, seed=cfg.seed,
                                 iterations=cfg.plane_iterations),
        "normal_entropy": M.normal_entropy(p5, voxel=0, radius=cfg.normal_radius * cfg.shape_voxel,
                                           max_nn=cfg.normal_max_nn, n_cells=cfg.n_cells),
    }


def fragment_stats(src: Source, cfg: StatsConfig, progress: bool = True) -> dict[str, Any]:
    """Measures over ``cfg.fragments`` fragments spread evenly over the column's fragments."""
    chosen = evenly(src.fragments, cfg.fragments)
    per = []
    for f in tqdm(chosen, desc=f"fragments {src.name}", unit="frag", disable=not progress, leave=False):
        pts, _ = read_cloud(f.path)
        per.append(fragment_measures(pts, cfg))
    ext = np.array([m["extent_pca"] for m in per])
    xyz = np.array([m["extent_xyz"] for m in per])
    return {
        "count": len(src.fragments),
        "scenes": len({f.scene for f in src.fragments}),
        "measured": len(per),
        "points": M.summarize(m["points"] for m in per),
        "extent_pca_median": np.median(ext, 0).tolist(),
        "extent_xyz_median": np.median(xyz, 0).tolist(),
        "planarity": M.summarize(m["planarity"] for m in per),
        "normal_entropy": M.summarize(m["normal_entropy"] for m in per),
        "normal_entropy_max": M.max_orientation_entropy(cfg.n_cells),
    }


def preview_fragments(src: Source, n: int = 3) -> list[dict[str, Any]]:
    """Up to ``n`` fragments for the picture: first, middle and last of the first benchmark scene
    (else the first scene), at 2.5 cm, with their colors (None when the file has none)."""
    import open3d as o3d

    scenes = [s for b in BENCHMARKS for s in sorted(src.benchmark_dirs.get(b, {}))]
    have = {f.scene for f in src.fragments}
    scene = next((s for s in scenes if s in have), src.fragments[0].scene)
    refs = [f for f in src.fragments if f.scene == scene]
    out = []
    for f in evenly(refs, n):
        pts, cols = read_cloud(f.path)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
        has_col = cols is not None and float(np.ptp(cols)) > 1e-6
        if has_col:
            pcd.colors = o3d.utility.Vector3dVector(np.clip(cols.astype(np.float64), 0, 1))
        d = pcd.voxel_down_sample(0.025)
        out.append({"scene": f.scene, "index": f.index, "points": np.asarray(d.points),
                    "colors": np.asarray(d.colors) if has_col else None})
    return out


# --------------------------------------------------------------------------- pairs


def _hist(overlaps: list[float]) -> dict[str, Any]:
    o = np.asarray(overlaps, dtype=np.float64)
    fin = o[np.isfinite(o)]
    return {"n": int(len(o)), "n_with_overlap": int(len(fin)), "counts": M.overlap_histogram(fin),
            "median": float(np.median(fin)) if len(fin) else None}


def pair_motion(pairs: list[PairRecord]) -> dict[str, Any]:
    """How far apart the two fragments' first cameras are: ``rotation_deg`` and ``translation_m`` of
    the pairs' ground-truth transforms (:func:`~pcrcg.data.stats.measures.summarize` of each)."""
    from pcrcg.geometry import rotation_angle_deg

    T = [np.asarray(p.transform, dtype=np.float64) for p in pairs]
    return {"rotation_deg": M.summarize(rotation_angle_deg(t[:3, :3]) for t in T),
            "translation_m": M.summarize(float(np.linalg.norm(t[:3, 3])) for t in T)}


def overlap_stats(src: Source) -> dict[str, Any]:
    """Overlap histograms (bins :data:`~pcrcg.data.stats.measures.OVERLAP_EDGES`) of each benchmark's
    pairs (``gt.log`` pairs, overlaps from ``gt_overlap.log``) with their relative motion
    (:func:`pair_motion`), and of the training pairs."""
    out: dict[str, Any] = {"edges": list(M.OVERLAP_EDGES)}
    for b in BENCHMARKS:
        pairs = src.benchmark_pairs(b)
        out[b] = {**_hist([p.overlap for p in pairs]), **pair_motion(pairs)} if pairs else None
    tr = src.train_overlaps()
    out["train"] = _hist(tr) if tr else None
    return out


def selected_pairs(src: Source, n: int | None) -> dict[str, dict[str, Any]]:
    """Per benchmark: the pairs whose two fragments the column has (``available``) and at most
    ``n`` of them spread evenly (``selected``); ``listed`` counts every gt.log pair."""
    out = {}
    for b in BENCHMARKS:
        pairs = src.benchmark_pairs(b)
        if not pairs:
            continue
        avail = [p for p in pairs if src.fragment(p.scene, p.i) and src.fragment(p.scene, p.j)]
        out[b] = {"listed": len(pairs), "available": avail, "selected": evenly(avail, n)}
    return out


# --------------------------------------------------------------------------- N against fragment size


def profile_sampling(profile: str) -> tuple[float, tuple[int, ...]]:
    """(model voxel in m, the protocol's sample sizes N) of ``conf/profile/<profile>.yaml``."""
    cfg = evaluate_config(profile)
    return float(cfg.profile.model.voxel_size), tuple(int(n) for n in cfg.profile.eval.n_points)


def model_points(path: str | Path, voxel: float) -> int:
    """Points of the fragment file ``path`` after the network's first grid subsampling at ``voxel`` (m):
    the points the protocol samples N from (``pcrcg.models.kpconv.ops.grid_subsample``)."""
    from pcrcg.models.kpconv.ops import grid_subsample

    pts, _ = read_cloud(path)
    return int(len(grid_subsample(pts, voxel)))


def below_n(smaller: np.ndarray, n_points: Sequence[int]) -> dict[int, float]:
    """Share of pairs (smaller: (P,) the point count of each pair's smaller fragment) with fewer than N
    points, for each N; {} without pairs."""
    smaller = np.asarray(smaller)
    return {int(n): float(np.mean(smaller < n)) for n in n_points} if len(smaller) else {}


def sampling_stats(src: Source, sel: dict[str, dict[str, Any]], voxel: float, n_points: Sequence[int],
                   progress: bool = True) -> dict[str, Any]:
    """How the protocol's N compare with the fragments the network sees: per benchmark, over every pair
    whose fragments the column has, the points of each fragment after the network's first grid
    subsampling (``pcrcg.models.kpconv.ops.grid_subsample`` at the model voxel) and, per N, the share of
    pairs whose smaller fragment has fewer than N points. Predator's protocol draws such a fragment's N
    points uniformly with replacement (``registration.fewer_points``), not by overlap x matchability: at
    that N the learned sampling is off."""
    counts: dict[tuple[str, int], int] = {}

    def points(scene: str, index: int) -> int:
        if (scene, index) not in counts:
            counts[(scene, index)] = model_points(src.fragment(scene, index).path, voxel)
        return counts[(scene, index)]

    out: dict[str, Any] = {"voxel": voxel, "n_points": [int(n) for n in n_points]}
    for b, s in sel.items():
        pairs = s["available"]
        smaller = np.array([min(points(p.scene, p.i), points(p.scene, p.j))
                            for p in tqdm(pairs, desc=f"N vs points {src.name} {b}", unit="pair",
                                          disable=not progress, leave=False)], dtype=np.int64)
        out[b] = {"pairs": int(len(smaller)), "smaller_points": M.summarize(smaller.tolist()),
                  "below": below_n(smaller, n_points)}
    return out


# --------------------------------------------------------------------------- FPFH + RANSAC


def evaluate_config(profile: str):
    """``conf/evaluate.yaml`` composed as ``python -m pcrcg.evaluate mode=benchmark method=fpfh
    profile=<profile>`` composes it."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from pcrcg.config import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR).resolve()), version_base="1.3"):
        return compose("evaluate", ["mode=benchmark", "method=fpfh", f"profile={profile}"])


def _link_or_write(ref: FragmentRef, dest: Path) -> None:
    from pcrcg.data.layout import write_ply

    dest.parent.mkdir(parents=True, exist_ok=True)
    if dest.exists():
        return
    if ref.path.suffix.lower() == ".ply":
        dest.symlink_to(ref.path.resolve())
    else:
        pts, cols = read_cloud(ref.path)
        write_ply(dest, pts, cols)


def write_subset_layout(src: Source, chosen: dict[str, list[PairRecord]], root: Path) -> Path:
    """A layout root holding only the chosen pairs: filtered ``gt.log``/``gt.info``/``gt_overlap.log``
    and links to the fragments, so that the project's benchmark runner scores exactly them."""
    from pcrcg.data.layout import write_gt_info, write_gt_log, write_gt_overlap

    layout = Layout(root)
    for b, pairs in chosen.items():
        by_scene: dict[str, list[PairRecord]] = defaultdict(list)
        for p in pairs:
            by_scene[p.scene].append(p)
        for scene, recs in by_scene.items():
            sdir = src.benchmark_dirs[b][scene]
            infos = read_gt_info(sdir / "gt.info")
            d = layout.benchmark_dir(b, scene)
            d.mkdir(parents=True, exist_ok=True)
            write_gt_log(d / "gt.log", recs)
            write_gt_info(d / "gt.info", recs, [infos[(p.i, p.j)] for p in recs])
            write_gt_overlap(d / "gt_overlap.log", recs)
            for p in recs:
                for i in (p.i, p.j):
                    _link_or_write(src.fragment(scene, i), layout.fragment(scene, i))
    return root


def fpfh_stats(src: Source, sel: dict[str, dict[str, Any]], cfg: StatsConfig, eval_cfg=None,
               progress: bool = True) -> dict[str, Any] | None:
    """FPFH + RANSAC registration recall per benchmark on the selected pairs, through the project's
    own path (:func:`pcrcg.evaluation.stage.run_benchmark_mode` with the settings of ``python -m
    pcrcg.evaluate mode=benchmark method=fpfh``); None without benchmark pairs."""
    from omegaconf import OmegaConf

    from pcrcg.evaluation.stage import configs_from, run_benchmark_mode

    chosen = {b: s["selected"] for b, s in sel.items() if s["selected"]}
    if not chosen:
        return None
    eval_cfg = eval_cfg if eval_cfg is not None else evaluate_config(cfg.profile)
    rcfg, bcfg = configs_from(eval_cfg)
    with tempfile.TemporaryDirectory(prefix="pcrcg-stats-") as tmp:
        root = write_subset_layout(src, chosen, Path(tmp) / "root")
        summary = run_benchmark_mode(
            "fpfh", root, Path(tmp) / "out", list(chosen), rcfg=rcfg, bcfg=bcfg, seed=cfg.seed,
            thresholds=OmegaConf.to_container(eval_cfg.eval, resolve=True),
            predator_variant=bool(eval_cfg.predator_variant), progress=progress,
        )
    out: dict[str, Any] = {"settings": {"fpfh": dataclasses.asdict(bcfg.fpfh),
                                        "ransac": dataclasses.asdict(bcfg.ransac), "profile": cfg.profile,
                                        "seed": cfg.seed}}
    for b, s in sel.items():
        e = summary["benchmarks"].get(b)
        base = {"listed": s["listed"], "available": len(s["available"]), "pairs": len(s["selected"])}
        if e is None:
            out[b] = {**base, "counted": 0, "success": 0, "rr": None, "rr_pair": None}
            continue
        out[b] = {**base, "counted": e["n_counted"], "success": e["n_success"], "rr": e["rr"],
                  "rr_pair": e["rr_pair"], "fmr": e.get("fmr"), "ir": e.get("ir"),
                  "seconds_per_pair": e.get("seconds_per_pair")}
    return out


# --------------------------------------------------------------------------- images


def matcher_configs(profile: str) -> dict[str, Any]:
    """``matcher2d=sift`` as ``python -m pcrcg.run matcher2d=sift profile=<profile>`` composes it (its
    ``image_size`` is the profile's ``lifting.image_size``, the projection's grid) and the same at the
    images' native size."""
    from omegaconf import OmegaConf

    from pcrcg.config import load_run_config
    from pcrcg.vision.matching import MatcherConfig

    cfg = load_run_config([f"profile={profile}", "matcher2d=sift"], validate=False)
    m = OmegaConf.to_container(cfg.matcher2d, resolve=True)
    grid = MatcherConfig.from_cfg(m)
    native = MatcherConfig.from_cfg({**m, "image_size": None})
    return {"grid": grid, "native": native}


def count_keypoints(img: np.ndarray, mcfg) -> int:
    """SIFT keypoints the project's matcher detects in an RGB image (H, W, 3) uint8 at its size."""
    from pcrcg.vision.matching import _detect, _gray

    return int(len(_detect(_gray(img, mcfg.image_size)[0], mcfg)[0]))


def view_pairs_of(src: Source, pairs: list[PairRecord]) -> tuple[list[tuple[Path, Path]], int]:
    """Color images of the paper's view pairs (first-first, last-last) of each pair's fragments
    (source j, target i) and the number of view pairs left out (no frame range or no image)."""
    out, skipped = [], 0
    for p in pairs:
        ij, ii = src.infos.get((p.scene, p.j)), src.infos.get((p.scene, p.i))
        if ij is None or ii is None:
            skipped += 2
            continue
        for fj, fi in ((ij.first_frame, ii.first_frame), (ij.last_frame, ii.last_frame)):
            a, b = src.frame_prefix(p.scene, ij.seq, fj), src.frame_prefix(p.scene, ii.seq, fi)
            ca, cb = (color_path(a) if a else None), (color_path(b) if b else None)
            if ca is None or cb is None:
                skipped += 1
                continue
            out.append((ca, cb))
    return out, skipped


def view_covisibility(src: Source, a: Path, b: Path) -> float:
    """:func:`measures.covisibility` of two frames given by their color images (depth, pose and the
    scene's ``camera-intrinsics.txt`` beside them); NaN when one of those is missing."""
    from pcrcg.data.layout import read_intrinsics, read_pose

    pa, pb = (p.with_name(p.name.split(".color.")[0]) for p in (a, b))
    da, db = depth_path(pa), depth_path(pb)
    poses = [q.with_name(q.name + ".pose.txt") for q in (pa, pb)]
    intr = [d / "camera-intrinsics.txt" for d in (pa.parent, pa.parent.parent)]
    intr = [k for k in intr if k.is_file()]
    if da is None or db is None or not all(q.is_file() for q in poses) or not intr:
        return float("nan")
    return M.covisibility(read_depth(da), read_pose(poses[0]), read_depth(db), read_pose(poses[1]),
                          read_intrinsics(intr[0]))


def matches_by_covisibility(covis: list[float], matches: list[int]) -> list[dict[str, Any]]:
    """Per bin of :data:`measures.COVIS_EDGES` (the last closed): view pairs and their verified
    matches (mean, share with any), so that data sets whose pairs see each other more or less
    compare at equal co-visibility."""
    c, m = np.asarray(covis, dtype=np.float64), np.asarray(matches, dtype=np.float64)
    out = []
    edges = M.COVIS_EDGES
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        s = (c >= lo) & ((c <= hi) if k == len(edges) - 2 else (c < hi))
        out.append({"lo": lo, "hi": hi, "n": int(s.sum()),
                    "mean": float(m[s].mean()) if s.any() else None,
                    "verified_share": float(np.mean(m[s] > 0)) if s.any() else None})
    return out


def matches_by_benchmark(benchmarks: list[str], matches: list[int]) -> dict[str, dict[str, Any]]:
    """Per benchmark of :data:`BENCHMARKS` that has view pairs: :func:`measures.summarize` of their
    verified matches and the share with any (``benchmarks[k]`` is the benchmark of view pair k)."""
    b, m = np.asarray(benchmarks, dtype=object), np.asarray(matches, dtype=np.float64)
    if len(b) != len(m):
        raise ValueError(f"{len(b)} benchmarks for {len(m)} view pairs")
    return {k: {**M.summarize(m[b == k]), "verified_share": float(np.mean(m[b == k] > 0))}
            for k in BENCHMARKS if np.any(b == k)}


def image_stats(src: Source, sel: dict[str, dict[str, Any]], cfg: StatsConfig,
                progress: bool = True) -> dict[str, Any] | None:
    """SIFT keypoints per image and verified matches per view pair (the project's matcher at the
    projection's grid and at native size) over the selected pairs' view pairs, and the view pairs'
    co-visibility (:func:`view_covisibility`) with the grid's matches per co-visibility bin and per
    benchmark (``grid_by_benchmark``: the view pairs of 3DMatch pairs and of 3DLoMatch pairs apart, so
    that data sets that mix the two in other proportions compare like with like). None without frames."""
    from pcrcg.vision.matching import match_images

    if not src.has_frames or not src.infos:
        return None
    vps, bench, skipped = [], [], 0
    for b in BENCHMARKS:
        if b in sel:
            v, s = view_pairs_of(src, sel[b]["selected"])
            vps += v
            bench += [b] * len(v)
            skipped += s
    if not vps:
        return None
    mcfgs = matcher_configs(cfg.profile)
    images: dict[Path, np.ndarray] = {}
    kp: dict[str, dict[Path, int]] = {k: {} for k in mcfgs}
    matches: dict[str, list[int]] = {k: [] for k in mcfgs}
    covis: list[float] = []
    for a, b in tqdm(vps, desc=f"SIFT {src.name}", unit="view pair", disable=not progress, leave=False):
        covis.append(view_covisibility(src, a, b))
        for p in (a, b):
            if p not in images:
                images[p] = read_rgb(p)
        for k, mc in mcfgs.items():
            for p in (a, b):
                if p not in kp[k]:
                    kp[k][p] = count_keypoints(images[p], mc)
            matches[k].append(len(match_images(images[a], images[b], mc)))
    shapes = sorted({f"{im.shape[1]}x{im.shape[0]}" for im in images.values()})
    out: dict[str, Any] = {"view_pairs": len(vps), "view_pairs_skipped": skipped, "images": len(images),
                           "native_size": shapes}
    for k, mc in mcfgs.items():
        size = f"{mc.image_size[1]}x{mc.image_size[0]}" if mc.image_size else "native"
        m = np.asarray(matches[k])
        out[k] = {"size": size, "keypoints": M.summarize(kp[k].values()), "matches": M.summarize(m),
                  "verified_share": float(np.mean(m > 0)), "min_matches": int(mc.min_matches),
                  "max_keypoints": int(mc.max_keypoints)}
    out["covisibility"] = M.summarize(covis)
    out["grid_by_covisibility"] = matches_by_covisibility(covis, matches["grid"])
    out["grid_by_benchmark"] = matches_by_benchmark(bench, matches["grid"])
    out["matcher"] = dataclasses.asdict(mcfgs["grid"])
    return out


def depth_stats(src: Source, cfg: StatsConfig) -> dict[str, Any] | None:
    """Share of zero-depth pixels per frame over at most ``cfg.frames`` frames of the measured
    fragments (their frame ranges, spread evenly), and under ``median_m`` the frames' median depth
    (how far the camera stands from what it scans). None without frames."""
    if not src.has_frames or not src.infos:
        return None
    frames = []
    for f in evenly(src.fragments, cfg.fragments):
        info = src.infos.get((f.scene, f.index))
        if info is None:
            continue
        for fid in info.frame_ids():
            pre = src.frame_prefix(f.scene, info.seq, fid)
            d = depth_path(pre) if pre is not None else None
            if d is not None:
                frames.append(d)
    frames = evenly(sorted(set(frames)), cfg.frames)
    if not frames:
        return None
    depths = [read_depth(p) for p in frames]
    rates = [M.hole_rate(d) for d in depths]
    return {**M.summarize(rates), "frames": len(frames), "median_m": M.summarize(M.median_depth(d) for d in depths)}


# --------------------------------------------------------------------------- one column


def measure(src: Source, cfg: StatsConfig, eval_cfg=None, progress: bool = True) -> dict[str, Any]:
    """Every measure of one column, with the seconds each stage took."""
    t: dict[str, float] = {}
    out: dict[str, Any] = {"name": src.name, "path": str(src.path), "kind": src.kind}
    t0 = time.perf_counter()
    out["fragments"] = fragment_stats(src, cfg, progress)
    t["fragments"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out["overlap"] = overlap_stats(src)
    sel = selected_pairs(src, cfg.pairs)
    t["overlap"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out["sampling"] = sampling_stats(src, sel, *profile_sampling(cfg.profile), progress=progress)
    t["sampling"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out["fpfh"] = fpfh_stats(src, sel, cfg, eval_cfg, progress) if cfg.fpfh else None
    t["fpfh"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out["sift"] = image_stats(src, sel, cfg, progress) if cfg.sift else None
    t["sift"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out["depth"] = depth_stats(src, cfg)
    t["depth"] = time.perf_counter() - t0
    out["seconds"] = {k: round(v, 2) for k, v in t.items()}
    out["summary"] = flat_summary(out)
    return out


def flat_summary(col: dict[str, Any]) -> dict[str, Any]:
    """The headline numbers of a column under flat keys (for checks against targets); None where
    the column has no such number."""
    def get(*keys):
        cur: Any = col
        for k in keys:
            if not isinstance(cur, dict) or cur.get(k) is None:
                return None
            cur = cur[k]
        return cur

    out = {
        "fragments": get("fragments", "count"),
        "points_mean": get("fragments", "points", "mean"),
        "points_p10": get("fragments", "points", "p10"),
        "points_p90": get("fragments", "points", "p90"),
        "extent_pca_median": get("fragments", "extent_pca_median"),
        "extent_xyz_median": get("fragments", "extent_xyz_median"),
        "planarity_median": get("fragments", "planarity", "median"),
        "planarity_min": get("fragments", "planarity", "min"),
        "planarity_max": get("fragments", "planarity", "max"),
        "normal_entropy_median": get("fragments", "normal_entropy", "median"),
        "train_overlap_median": get("overlap", "train", "median"),
        "sift_keypoints_grid_mean": get("sift", "grid", "keypoints", "mean"),
        "sift_keypoints_native_mean": get("sift", "native", "keypoints", "mean"),
        "sift_matches_grid_mean": get("sift", "grid", "matches", "mean"),
        "sift_matches_native_mean": get("sift", "native", "matches", "mean"),
        "depth_hole_rate_mean": get("depth", "mean"),
        "depth_median_m": get("depth", "median_m", "median"),
    }
    for b in BENCHMARKS:
        out[f"{b}_overlap_median"] = get("overlap", b, "median")
        out[f"{b}_fpfh_rr"] = get("fpfh", b, "rr")
        out[f"{b}_fpfh_counted"] = get("fpfh", b, "counted")
        for n, share in (get("sampling", b, "below") or {}).items():
            out[f"{b}_below_{n}"] = share
    return out
