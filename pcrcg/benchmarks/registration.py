"""Registration speed and recall: ours vs Predator's evaluation path, side by side in one run.

    python -m pcrcg.benchmarks.registration [--pairs 16] [--n-points 5000 2500 1000 500 250]

Pairs: two depth frames of the real Kinect sequence in ``../shared/data/real-rgbd/
redkitchen-frames`` back-projected and voxelised at 2.5 cm (Predator's voxel), cropped to
overlaps between ~15 % and ~75 %, the source moved into a random frame (a synthetic room when
the frames are absent). No trained network is available here, so the per-point outputs are
simulated: descriptors are random Fourier features of the world position plus noise (its level
sets the inlier ratio, from a few % to ~60 % over the pairs), overlap scores follow the true overlap
with noise, matchability is random. The registration code does not know this.

For every N it reports, per pair and averaged:

* **ours**: Gumbel-top-k sampling by overlap x matchability, torch nearest-neighbour matching,
  our batched RANSAC (confidence 0.999);
* **Predator's path**: ``np.random.choice(..., replace=False, p=...)`` sampling and Open3D's
  ``registration_ransac_based_on_feature_matching`` with Predator's arguments (no mutual filter,
  5 cm, 3 points, both checkers, ``RANSACConvergenceCriteria(50000, 1000)``, which Open3D 0.20
  reads as 50,000 iterations at confidence 1.0);
* **same correspondences**: our RANSAC (with Open3D's overlap ranking, and with the
  correspondence ranking) and Open3D's ``registration_ransac_based_on_correspondence`` on
  identical correspondence sets with identical settings (confidence 0.999).

Success = the 3DMatch criterion (``e^T info e / info[0,0] <= 0.2^2`` with ``info`` from the
pair's ground-truth overlap). Timings are wall-clock, interleaved pair by pair, with
``OMP_NUM_THREADS=1`` unless set (one core each: on a shared 2-core machine OpenMP with 2 threads
made both Open3D and torch many times slower and the figures noisy).
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
    from pcrcg.registration.synthetic import box_room

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
    from pcrcg.registration.pipeline import FragmentOutput

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


def main(argv: list[str] | None = None) -> dict:
    import dataclasses

    from pcrcg.evaluation.metrics import inlier_ratio
    from pcrcg.registration.pipeline import RegistrationConfig, pair_seed, register_features
    from pcrcg.registration.ransac import RansacConfig, ransac, ransac_open3d

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--n-points", type=int, nargs="+", default=[5000, 2500, 1000, 500, 250])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--iterations", type=int, default=50000)
    ap.add_argument("--seeds", type=int, default=3, help="RANSAC repeats per pair on identical correspondences")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    pairs, source = make_pairs(args.pairs, args.seed)
    print(f"{len(pairs)} pairs from {source}; {np.mean([len(p.src.points) for p in pairs]):.0f} points per "
          f"fragment on average; overlap {min(p.overlap for p in pairs):.2f}..{max(p.overlap for p in pairs):.2f} "
          f"(built in {time.perf_counter() - t0:.1f} s)")
    ours_cfg = RegistrationConfig(device=args.device, ransac=RansacConfig(max_iterations=args.iterations))
    pred_cfg = RansacConfig(max_iterations=args.iterations, confidence=1.0)  # (50000, 1000) in Open3D 0.20
    same_cfg = RansacConfig(max_iterations=args.iterations)
    corr_cfg = RansacConfig(max_iterations=args.iterations, score="correspondences")
    legacy = np.random.RandomState(args.seed)
    rows = []
    print("full path = sampling + matching + RANSAC; same corr. = RANSAC alone on identical correspondences "
          f"(ours with Open3D's overlap ranking / with correspondence ranking, Open3D), confidence 0.999, "
          f"{args.seeds} seeds per pair")
    print(f"{'N':>5} | {'IR %':>5} | {'ours s/pair':>11} {'RR %':>5} | {'Predator s/pair':>15} {'RR %':>5} | {'speed-up':>8} |"
          f" same corr.: {'ours s':>7} {'RR %':>5} {'ours-c s':>8} {'RR %':>5} {'Open3D s':>8} {'RR %':>5} "
          f"{'O3D/ours':>8} {'O3D/ours-c':>10}")
    for n in args.n_points:
        acc = {k: [] for k in ("t_ours", "ok_ours", "t_pred", "ok_pred", "t_r_ours", "ok_r_ours", "t_r_corr", "ok_r_corr",
                               "t_r_o3d", "ok_r_o3d", "ir")}
        for k, p in enumerate(pairs):
            s0 = time.perf_counter()
            reg = register_features(p.src, p.tgt, n, ours_cfg, seed=pair_seed(args.seed, "bench", k, k + 1, n))
            acc["t_ours"].append(time.perf_counter() - s0)
            acc["ok_ours"].append(_success(reg.transform, p))
            c = reg.correspondences
            acc["ir"].append(inlier_ratio(p.src.points[c[:, 0]], p.tgt.points[c[:, 1]], p.transform))

            s0 = time.perf_counter()
            T_pred = _predator_path(p, n, legacy, pred_cfg)
            acc["t_pred"].append(time.perf_counter() - s0)
            acc["ok_pred"].append(_success(T_pred, p))

            # identical correspondences (ours' sampled points and matches) into both RANSACs
            sp, tp = p.src.points[reg.src_idx], p.tgt.points[reg.tgt_idx]
            loc = np.stack([np.searchsorted(reg.src_idx, c[:, 0]), np.searchsorted(reg.tgt_idx, c[:, 1])], 1)
            for rep in range(args.seeds):
                sd = 1000 * k + rep
                s0 = time.perf_counter()
                r1 = ransac(sp, tp, loc, same_cfg, seed=sd, device=args.device)
                acc["t_r_ours"].append(time.perf_counter() - s0)
                acc["ok_r_ours"].append(_success(r1.transform, p))
                s0 = time.perf_counter()
                r3 = ransac(sp, tp, loc, corr_cfg, seed=sd, device=args.device)
                acc["t_r_corr"].append(time.perf_counter() - s0)
                acc["ok_r_corr"].append(_success(r3.transform, p))
                s0 = time.perf_counter()
                r2 = ransac_open3d(sp, tp, loc, same_cfg, seed=sd)
                acc["t_r_o3d"].append(time.perf_counter() - s0)
                acc["ok_r_o3d"].append(_success(r2.transform, p))
        m = {k: float(np.mean(v)) for k, v in acc.items()}
        row = {
            "n_points": n, "inlier_ratio": 100 * m["ir"],
            "ours_s_per_pair": m["t_ours"], "ours_rr": 100 * m["ok_ours"],
            "predator_s_per_pair": m["t_pred"], "predator_rr": 100 * m["ok_pred"],
            "speedup": m["t_pred"] / m["t_ours"],
            "same_corr_ours_s": m["t_r_ours"], "same_corr_ours_rr": 100 * m["ok_r_ours"],
            "same_corr_ours_corrscore_s": m["t_r_corr"], "same_corr_ours_corrscore_rr": 100 * m["ok_r_corr"],
            "same_corr_open3d_s": m["t_r_o3d"], "same_corr_open3d_rr": 100 * m["ok_r_o3d"],
            "same_corr_ratio": m["t_r_o3d"] / m["t_r_ours"],
            "same_corr_ratio_corrscore": m["t_r_o3d"] / m["t_r_corr"],
        }
        rows.append(row)
        print(f"{n:>5} | {row['inlier_ratio']:5.1f} | {row['ours_s_per_pair']:11.4f} {row['ours_rr']:5.1f} | "
              f"{row['predator_s_per_pair']:15.4f} {row['predator_rr']:5.1f} | {row['speedup']:7.1f}x |"
              f"             {row['same_corr_ours_s']:7.4f} {row['same_corr_ours_rr']:5.1f} "
              f"{row['same_corr_ours_corrscore_s']:8.4f} {row['same_corr_ours_corrscore_rr']:5.1f} "
              f"{row['same_corr_open3d_s']:8.4f} {row['same_corr_open3d_rr']:5.1f} {row['same_corr_ratio']:7.1f}x "
              f"{row['same_corr_ratio_corrscore']:9.1f}x", flush=True)
    tot_ours = sum(r["ours_s_per_pair"] for r in rows)
    tot_pred = sum(r["predator_s_per_pair"] for r in rows)
    summary = {
        "pairs": len(pairs), "source": source, "n_points": args.n_points, "rows": rows,
        "total_ours_s_per_pair": tot_ours, "total_predator_s_per_pair": tot_pred, "total_speedup": tot_pred / tot_ours,
        "mean_rr_ours": float(np.mean([r["ours_rr"] for r in rows])),
        "mean_rr_predator": float(np.mean([r["predator_rr"] for r in rows])),
        "settings": {"ours": dataclasses.asdict(ours_cfg.ransac), "predator": dataclasses.asdict(pred_cfg)},
    }
    print(f"all N: ours {tot_ours:.3f} s/pair, Predator's path {tot_pred:.3f} s/pair -> {summary['total_speedup']:.1f}x faster; "
          f"mean RR ours {summary['mean_rr_ours']:.1f} % vs Predator {summary['mean_rr_predator']:.1f} %")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
