"""Registration speed and recall: ours vs Predator's evaluation path, side by side in one run.

    python -m pcrcg.benchmarks.registration [--pairs 16] [--n-points 5000 2500 1000 500 250] [--seeds 3]
        [--identical-only]

Pairs: two depth frames of the real Kinect sequence in ``../shared/data/real-rgbd/
redkitchen-frames`` back-projected and voxelised at 2.5 cm (Predator's voxel), cropped to
overlaps between ~15 % and ~75 %, the source moved into a random frame (a synthetic room when
the frames are absent). No trained network is available here, so the per-point outputs are
simulated: descriptors are random Fourier features of the world position plus noise (its level
sets the inlier ratio, from a few % to ~60 % over the pairs), overlap scores follow the true overlap
with noise, matchability is random. The registration code does not know this.

For every N it reports, per pair and averaged:

* **ours**: Gumbel-top-k sampling by overlap x matchability, torch nearest-neighbour matching,
  our batched RANSAC with the default settings (Open3D's overlap ranking, confidence 0.999);
  **ours-fast** ranks by inlier correspondences; **ours-50k** also runs every one of the 50,000
  iterations, as Predator's path does;
* **Predator's path**: ``np.random.choice(..., replace=False, p=...)`` sampling and Open3D's
  ``registration_ransac_based_on_feature_matching`` with Predator's arguments (no mutual filter,
  5 cm, 3 points, both checkers, ``RANSACConvergenceCriteria(50000, 1000)``, which Open3D 0.20
  reads as 50,000 iterations at confidence 1.0);
* **same correspondences**: our RANSAC (with Open3D's overlap ranking, and with the
  correspondence ranking) and Open3D's ``registration_ransac_based_on_correspondence`` on
  identical correspondence sets with identical settings (confidence 0.999).

The process is pinned to ``--cores`` CPUs (default 1; every thread, Open3D's included: with
``OMP_NUM_THREADS=1`` alone Open3D's RANSAC still took ~1.8x its wall time in CPU time on 2 cores, 2026-12-07), so
wall-time ratios compare the same cores; ``--cores 0`` leaves the process free.

Success = the 3DMatch criterion (``e^T info e / info[0,0] <= 0.2^2`` with ``info`` from the
pair's ground-truth overlap). Timings are wall-clock, interleaved pair by pair, with
``OMP_NUM_THREADS=1`` unless set (one core each: on a shared 2-core machine OpenMP with 2 threads
made both Open3D and torch many times slower and the figures noisy); the identical-correspondence table
also gives each RANSAC's CPU seconds (the process's, so a library's extra threads count), which a busy
machine inflates less than wall time: beside two sweep jobs (2026-12-07) the wall-time ratio at N = 500 was
2.8x where the same calls' CPU-time ratio was ~4.4x.
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # before NumPy / torch / Open3D start their thread pools
    os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
FRAMES = SHARED / "data" / "real-rgbd" / "redkitchen-frames"


@dataclass
class SimPair:
    """One benchmark pair: clouds in their own frames, simulated outputs, ground truth."""

    src: object  # FragmentOutput
    tgt: object
    transform: np.ndarray  # (4, 4) source -> target
    info: np.ndarray  # (6, 6)
    overlap: float


def _voxel(points: np.ndarray, voxel: float) -> np.ndarray:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    return np.asarray(pcd.voxel_down_sample(voxel).points)


def _frame_clouds(rng: np.random.Generator, n_pairs: int):
    """[(src_world (N,3), tgt_world (M,3), T_world_src_cam, T_world_tgt_cam)] from the real frames."""
    from pcrcg.data.layout import read_depth, read_intrinsics, read_pose
    from pcrcg.geometry import backproject, transform_points

    K = read_intrinsics(FRAMES / "camera-intrinsics.txt")
    ids = list(range(8, 48))
    cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def frame(k: int):
        if k not in cache:
            depth = read_depth(FRAMES / f"frame-{k:06d}.depth.png")
            pose = read_pose(FRAMES / f"frame-{k:06d}.pose.txt")
            pts, vu = backproject(depth, K, stride=2)
            cache[k] = (pts, vu, pose)
        return cache[k]

    out = []
    W = 640
    for _ in range(n_pairs):
        a, b = sorted(rng.choice(ids, size=2, replace=False))
        crop = rng.uniform(0.15, 0.42)
        pa, vua, Pa = frame(int(a))
        pb, vub, Pb = frame(int(b))
        sa = pa[vua[:, 1] < W * (1 - crop)]  # source keeps the left part of its image
        sb = pb[vub[:, 1] > W * crop]  # target the right part
        out.append((transform_points(Pa, sa), transform_points(Pb, sb)))
    return out


def _room_clouds(rng: np.random.Generator, n_pairs: int):
    """Fallback without ../shared: a synthetic room, split into overlapping parts."""
    from pcrcg.testing.rooms import box_room

    room, _ = box_room(rng, 120000)
    lo, hi = room[:, 0].min(), room[:, 0].max()
    out = []
    for _ in range(n_pairs):
        crop = rng.uniform(0.15, 0.42)
        out.append((room[room[:, 0] < lo + (hi - lo) * (1 - crop)], room[room[:, 0] > lo + (hi - lo) * crop]))
    return out


def make_pairs(n_pairs: int, seed: int = 0, voxel: float = 0.025, dim: int = 32) -> tuple[list[SimPair], str]:
    """Benchmark pairs with simulated network outputs (see the module docstring)."""
    from scipy.spatial import cKDTree

    from pcrcg.evaluation.metrics import information_matrix
    from pcrcg.geometry import invert, make_transform, random_rotation, transform_points
    from pcrcg.registration.feature_registration import FragmentOutput

    rng = np.random.default_rng(seed)
    source = "redkitchen frames" if (FRAMES / "camera-intrinsics.txt").is_file() else "synthetic room"
    clouds = _frame_clouds(rng, n_pairs) if source.startswith("redkitchen") else _room_clouds(rng, n_pairs)
    Wf = rng.normal(scale=1.0 / 0.06, size=(dim, 3))
    bf = rng.uniform(0, 2 * np.pi, size=dim)

    def describe(world: np.ndarray, noise: float) -> np.ndarray:
        d = np.cos(world @ Wf.T + bf) + rng.normal(scale=noise, size=(len(world), dim))
        return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)

    pairs = []
    for k, (sw, tw) in enumerate(clouds):
        sw, tw = _voxel(sw, voxel), _voxel(tw, voxel)
        d_s, _ = cKDTree(tw).query(sw)
        d_t, _ = cKDTree(sw).query(tw)
        ov_s, ov_t = d_s < 1.5 * voxel, d_t < 1.5 * voxel
        noise = 0.3 + 2.5 * (k % 8) / 7.0  # spans easy to hard pairs
        # fragment frames: target = world shifted to its centroid; source = a random rigid frame
        T_t = make_transform(np.eye(3), -tw.mean(0))
        T_s = make_transform(random_rotation(rng), rng.normal(scale=0.5, size=3)) @ make_transform(np.eye(3), -sw.mean(0))
        src_pts, tgt_pts = transform_points(T_s, sw), transform_points(T_t, tw)
        T_gt = T_t @ invert(T_s)  # source frame -> world -> target frame

        def scores(ov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            o = np.clip(0.15 + 0.75 * ov * rng.uniform(0.6, 1.0, len(ov)) + rng.normal(0, 0.08, len(ov)), 0.01, 1)
            return o.astype(np.float32), rng.uniform(0.2, 1.0, len(ov)).astype(np.float32)

        so, sm = scores(ov_s)
        to, tm = scores(ov_t)
        src = FragmentOutput(src_pts.astype(np.float32), describe(sw, noise), so, sm)
        tgt = FragmentOutput(tgt_pts.astype(np.float32), describe(tw, noise), to, tm)
        info = information_matrix(src_pts[ov_s])  # residual motion acts in the source frame
        pairs.append(SimPair(src, tgt, T_gt, info, float(min(ov_s.mean(), ov_t.mean()))))
    return pairs, source


def _success(T_est: np.ndarray, p: SimPair) -> bool:
    from pcrcg.evaluation.metrics import registration_error

    return bool(registration_error(T_est, p.transform, p.info) <= 0.2**2)


def _predator_path(p: SimPair, n: int, rng: np.random.RandomState, cfg) -> np.ndarray:
    """Predator's evaluate_predator.py steps 2-3 (sampling + Open3D feature-matching RANSAC)."""
    from pcrcg.registration.ransac import ransac_feature_matching_open3d

    def pick(f):
        if len(f.points) <= n:
            return f.points, f.descriptors
        s = f.scores().astype(np.float64)
        idx = rng.choice(np.arange(len(s)), size=n, replace=False, p=s / s.sum())
        return f.points[idx], f.descriptors[idx]

    sp, sd = pick(p.src)
    tp, td = pick(p.tgt)
    return ransac_feature_matching_open3d(sp, tp, sd, td, cfg, mutual=False, seed=int(rng.randint(1 << 30))).transform


OURS = {  # name -> RansacConfig overrides of the full path
    "ours": {},  # the default: Open3D's overlap ranking, confidence 0.999
    "ours-fast": {"score": "correspondences"},
    "ours-50k": {"score": "correspondences", "confidence": 1.0},  # every iteration, like Predator's path
}


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--n-points", type=int, nargs="+", default=[5000, 2500, 1000, 500, 250])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--iterations", type=int, default=50000)
    ap.add_argument("--seeds", type=int, default=3, help="RANSAC repeats per pair on identical correspondences")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--identical-only", action="store_true",
                    help="only the identical-correspondences table (the full path runs once, for the correspondences; "
                         "no ours-fast, ours-50k or Predator's path)")
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    ap.add_argument("--cores", type=int, default=1,
                    help="CPUs the process (every thread, Open3D's too) is pinned to, so both RANSACs work on the same "
                         "cores; 0: not pinned")
    return ap.parse_args(argv)


def _full_paths(p: SimPair, k: int, n: int, ours: dict, legacy: np.random.RandomState, pred_cfg, acc: dict,
                seed: int, with_predator: bool):
    """Every full path on pair p (index k) at N = n, timed into ``acc``; returns the default path's registration."""
    from pcrcg.evaluation.metrics import inlier_ratio
    from pcrcg.registration.feature_registration import pair_seed, register_features

    sd = pair_seed(seed, "bench", k, k + 1, n)
    first = None
    for name, cfg in ours.items():
        s0 = time.perf_counter()
        reg = register_features(p.src, p.tgt, n, cfg, seed=sd)
        acc[f"t_{name}"].append(time.perf_counter() - s0)
        acc[f"ok_{name}"].append(_success(reg.transform, p))
        first = reg if name == "ours" else first
    c = first.correspondences
    acc["ir"].append(inlier_ratio(p.src.points[c[:, 0]], p.tgt.points[c[:, 1]], p.transform))
    if with_predator:
        s0 = time.perf_counter()
        T_pred = _predator_path(p, n, legacy, pred_cfg)
        acc["t_predator"].append(time.perf_counter() - s0)
        acc["ok_predator"].append(_success(T_pred, p))
    return first


def _identical(p: SimPair, k: int, first, base, corr_cfg, acc: dict, seeds: int, device: str) -> None:
    """The default path's samples and matches into our RANSAC (overlap and correspondence ranking) and
    Open3D's, ``seeds`` times each, timed into ``acc``."""
    from pcrcg.registration.ransac import ransac, ransac_open3d

    c = first.correspondences
    sp, tp = p.src.points[first.src_idx], p.tgt.points[first.tgt_idx]
    loc = np.stack([np.searchsorted(first.src_idx, c[:, 0]), np.searchsorted(first.tgt_idx, c[:, 1])], 1)
    for rep in range(seeds):
        rs = 1000 * k + rep
        for key, fn in (("ov", lambda: ransac(sp, tp, loc, base, seed=rs, device=device)),
                        ("c", lambda: ransac(sp, tp, loc, corr_cfg, seed=rs, device=device)),
                        ("o3d", lambda: ransac_open3d(sp, tp, loc, base, seed=rs))):
            s0, c0 = time.perf_counter(), time.process_time()
            T = fn().transform
            acc[f"t_s_{key}"].append(time.perf_counter() - s0)
            acc[f"cpu_s_{key}"].append(time.process_time() - c0)
            acc[f"ok_s_{key}"].append(_success(T, p))


def _row(n: int, acc: dict, names: list[str]) -> dict:
    """One N's means: seconds per pair and RR of each path, the identical-correspondence figures."""
    m = {k: float(np.mean(v)) for k, v in acc.items() if v}
    row = {"n_points": n, "inlier_ratio": 100 * m["ir"]}
    for name in names:
        row[f"{name}_s_per_pair"] = m[f"t_{name}"]
        row[f"{name}_rr"] = 100 * m[f"ok_{name}"]
    if "predator" in names:
        row["speedup_vs_predator"] = m["t_predator"] / m["t_ours"]
    for key, label in (("ov", "same_ours"), ("c", "same_ours_fast"), ("o3d", "same_open3d")):
        row[f"{label}_s"] = m[f"t_s_{key}"]
        row[f"{label}_cpu_s"] = m[f"cpu_s_{key}"]
        row[f"{label}_rr"] = 100 * m[f"ok_s_{key}"]
    return row


def _full_line(row: dict, names: list[str]) -> str:
    line = f"{row['n_points']:>5} {row['inlier_ratio']:5.1f} | " + " | ".join(
        f"{row[f'{k}_s_per_pair']:11.4f} {row[f'{k}_rr']:5.1f}" for k in names)
    return line + (f" | {row['speedup_vs_predator']:12.1f}x" if "predator" in names else "")


def _identical_line(row: dict) -> str:
    return (f"{row['n_points']:>5} | {row['same_ours_s']:8.4f} {row['same_ours_rr']:5.1f} | {row['same_ours_fast_s']:8.4f} "
            f"{row['same_ours_fast_rr']:5.1f} | {row['same_open3d_s']:8.4f} {row['same_open3d_rr']:5.1f} | "
            f"{row['same_open3d_s'] / row['same_ours_s']:7.1f}x {row['same_open3d_s'] / row['same_ours_fast_s']:9.1f}x | "
            f"{row['same_ours_cpu_s']:8.4f} {row['same_open3d_cpu_s']:8.4f} {row['same_open3d_cpu_s'] / row['same_ours_cpu_s']:7.1f}x")


def main(argv: list[str] | None = None) -> dict:
    import dataclasses

    from pcrcg.registration.feature_registration import RegistrationConfig
    from pcrcg.device import pin_cores
    from pcrcg.errors import ConfigError
    from pcrcg.registration.ransac import RansacConfig

    args = _arguments(argv)
    if args.cores < 0:
        raise ConfigError("--cores", args.cores, "an integer >= 0 (0: not pinned)")
    pinned = pin_cores(args.cores)
    print(f"pinned to CPU {', '.join(map(str, pinned))} (--cores {args.cores}): both RANSACs on the same cores"
          if pinned else "not pinned to CPUs (--cores 0, or not Linux): a library's own threads may use more cores")
    t0 = time.perf_counter()
    pairs, source = make_pairs(args.pairs, args.seed)
    print(f"{len(pairs)} pairs from {source}; {np.mean([len(p.src.points) for p in pairs]):.0f} points per "
          f"fragment on average; overlap {min(p.overlap for p in pairs):.2f}..{max(p.overlap for p in pairs):.2f} "
          f"(built in {time.perf_counter() - t0:.1f} s)")
    base = RansacConfig(max_iterations=args.iterations)
    used = ["ours"] if args.identical_only else list(OURS)
    ours = {k: RegistrationConfig(device=args.device, ransac=dataclasses.replace(base, **OURS[k])) for k in used}
    pred_cfg = dataclasses.replace(base, confidence=1.0)  # RANSACConvergenceCriteria(50000, 1000) in Open3D 0.20
    corr_cfg = dataclasses.replace(base, score="correspondences")
    legacy = np.random.RandomState(args.seed)
    names = used + ([] if args.identical_only else ["predator"])
    rows = []
    print("Full path (sampling + matching + RANSAC), seconds per pair and registration recall:")
    print(f"{'N':>5} {'IR %':>5} | " + " | ".join(f"{k:>9} s {'RR %':>5}" for k in names)
          + ("" if args.identical_only else f" | {'speed-up ours':>13}"))
    for n in args.n_points:
        acc: dict[str, list] = {k: [] for k in ["ir"] + [f"t_{k}" for k in names] + [f"ok_{k}" for k in names]
                                 + [f"{m}_s_{k}" for k in ("ov", "c", "o3d") for m in ("t", "cpu", "ok")]}
        for k, p in enumerate(pairs):
            first = _full_paths(p, k, n, ours, legacy, pred_cfg, acc, args.seed, not args.identical_only)
            _identical(p, k, first, base, corr_cfg, acc, args.seeds, args.device)
        rows.append(_row(n, acc, names))
        print(_full_line(rows[-1], names), flush=True)
    print(f"\nIdentical correspondences (the default path's), RANSAC alone, confidence 0.999, {args.seeds} seeds per pair:")
    print(f"{'N':>5} | {'ours s':>8} {'RR %':>5} | {'fast s':>8} {'RR %':>5} | {'Open3D s':>8} {'RR %':>5} | "
          f"{'O3D/ours':>8} {'O3D/fast':>9} | {'ours cpu':>8} {'O3D cpu':>8} {'O3D/ours':>8}")
    print("\n".join(_identical_line(r) for r in rows))
    tot = {name: sum(r[f"{name}_s_per_pair"] for r in rows) for name in names}
    summary = {
        "pairs": len(pairs), "source": source, "n_points": args.n_points, "seeds": args.seeds, "rows": rows,
        "total_s_per_pair": tot,
        "mean_rr": {name: float(np.mean([r[f"{name}_rr"] for r in rows])) for name in names},
        "settings": {name: dataclasses.asdict(c.ransac) for name, c in ours.items()} | {"predator": dataclasses.asdict(pred_cfg)},
    }
    if not args.identical_only:
        print("\nAll N together: " + ", ".join(
            f"{name} {tot[name]:.3f} s/pair (RR {summary['mean_rr'][name]:.1f} %, {tot['predator'] / tot[name]:.0f}x faster "
            f"than Predator's path)" for name in OURS) + f"; Predator's path {tot['predator']:.3f} s/pair "
            f"(RR {summary['mean_rr']['predator']:.1f} %)")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1))
    return summary

if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.benchmarks.registration"):  # a bad file or setting: one line, exit 2
        main()
