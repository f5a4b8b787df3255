"""Why a trained model's pairs fail to register: RANSAC's search or its ranking (prints figures; asserts nothing).

    python -m pcrcg.benchmarks.ranking CHECKPOINT [--root data/synthmatch-cpu] [--benchmarks 3DMatch 3DLoMatch]
        [--pairs 100] [--n-points 5000] [--profile cpu] [--distance D] [--seed 0]

Per pair (the pairs registration recall counts, :func:`pcrcg.evaluation.metrics.counted_mask`) at N points:
Predator's sampling and matching on the model's outputs, then RANSAC with Open3D 0.10's budget twice,
ranking its hypotheses by **overlap** (Open3D's fitness: the share of the N sampled source points with a
sampled target point within ``distance``, the paper's protocol) and by **inlier correspondences**
(``registration=inlier_ranking``). A registration fails when the 3DMatch RMSE exceeds 0.2 m; RR is the share
of the counted pairs (not averaged per scene). Each failure is then scored by the ranking that chose it, for
the chosen pose and for the ground truth:

* **ranking**: the chosen pose scores at least as high as the ground truth, so no larger budget finds the
  right pose: the criterion prefers a wrong one (e.g. a pose slid along a wall keeps most of the sampled
  points within the distance);
* **search**: the ground truth scores higher: the budget ended before a hypothesis near it was drawn.

Both rankings see the same samples and correspondences (the same seed per pair), so their difference in
recall is the ranking's alone. The registration settings are those ``python -m pcrcg.evaluate`` composes
for ``--profile`` (conf/registration/default.yaml: Open3D 0.10's budget, RANSAC distance 2x the profile's
voxel unless ``--distance``), so the overlap rows register as a run of that profile does.
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # before NumPy / torch start their thread pools
    os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import dataclasses
from collections import Counter
from pathlib import Path
from typing import Sequence

import numpy as np

RANKINGS = ("overlap", "correspondences")


def overlap_fitness(T: np.ndarray, src: np.ndarray, tgt: np.ndarray, distance: float) -> float:
    """T (4, 4), src (n, 3), tgt (m, 3) -> the share of ``T src`` with a point of ``tgt`` within ``distance``
    (Open3D's RANSAC fitness on the sampled clouds)."""
    from scipy.spatial import cKDTree

    if len(src) == 0 or len(tgt) == 0:
        return 0.0
    moved = src @ T[:3, :3].T + T[:3, 3]
    d, _ = cKDTree(tgt).query(moved, k=1, distance_upper_bound=distance)
    return float((d < distance).mean())


def inlier_count(T: np.ndarray, src_c: np.ndarray, tgt_c: np.ndarray, distance: float) -> int:
    """T (4, 4), correspondences as coordinates src_c (K, 3) -> tgt_c (K, 3): how many lie within ``distance``
    after ``T`` (the protocol's :func:`pcrcg.evaluation.metrics.inlier_ratio`, as a count)."""
    from pcrcg.evaluation.metrics import inlier_ratio

    return int(round(inlier_ratio(src_c, tgt_c, T, distance) * len(src_c)))


def ranking_score(ranking: str, T: np.ndarray, src: np.ndarray, tgt: np.ndarray, src_c: np.ndarray,
                  tgt_c: np.ndarray, distance: float) -> float:
    """The score by which RANSAC ranking ``ranking`` (overlap | correspondences) orders hypothesis ``T``:
    src (n, 3) / tgt (m, 3) the sampled clouds, src_c / tgt_c (K, 3) the correspondences' coordinates."""
    if ranking == "overlap":
        return overlap_fitness(T, src, tgt, distance)
    if ranking == "correspondences":
        return float(inlier_count(T, src_c, tgt_c, distance))
    raise ValueError(f"ranking must be one of {RANKINGS}, got {ranking!r}")


def failure_kind(ranking: str, T_est: np.ndarray, T_gt: np.ndarray, src: np.ndarray, tgt: np.ndarray,
                 src_c: np.ndarray, tgt_c: np.ndarray, distance: float) -> str:
    """``ranking`` when the chosen pose ``T_est`` scores at least as high as ``T_gt`` under the ranking that
    chose it, else ``search``. Shapes as :func:`ranking_score`."""
    chosen = ranking_score(ranking, T_est, src, tgt, src_c, tgt_c, distance)
    truth = ranking_score(ranking, T_gt, src, tgt, src_c, tgt_c, distance)
    return "ranking" if chosen >= truth else "search"


@dataclasses.dataclass
class Tally:
    """One benchmark under one ranking: counted pairs, registered, and failures by kind."""

    pairs: int = 0
    registered: int = 0
    kinds: Counter = dataclasses.field(default_factory=Counter)

    def add(self, ok: bool, kind: str | None) -> None:
        self.pairs += 1
        self.registered += int(ok)
        if not ok:
            self.kinds[kind] += 1

    def row(self, benchmark: str, ranking: str) -> str:
        rr = 100.0 * self.registered / self.pairs if self.pairs else float("nan")
        failed = self.pairs - self.registered
        return (f"{benchmark:<10} {ranking:<16} {self.pairs:>5} {rr:>7.1f} {failed:>6} "
                f"{self.kinds['ranking']:>8} {self.kinds['search']:>7}")


def diagnose_pair(src, tgt, T_gt: np.ndarray, info: np.ndarray, n_points: int, cfg,
                  seed) -> dict[str, tuple[bool, str | None]]:
    """One pair (:class:`pcrcg.registration.FragmentOutput` each), every ranking: (registered, failure kind or
    None). ``cfg``: the run's :class:`RegistrationConfig`; ``seed``: the pair's ``SeedSequence``."""
    from pcrcg.evaluation.metrics import RMSE_THRESHOLD, registration_error
    from pcrcg.registration.feature_registration import register_features

    out = {}
    for ranking in RANKINGS:
        rc = dataclasses.replace(cfg, ransac=dataclasses.replace(cfg.ransac, score=ranking))
        reg = register_features(src, tgt, n_points, rc, seed=seed)  # the same samples for both rankings
        ok = bool(registration_error(reg.transform, T_gt, info) <= RMSE_THRESHOLD ** 2)
        kind = None
        if not ok:
            c = reg.correspondences  # indices into the fragments
            kind = failure_kind(ranking, reg.transform, T_gt, src.points[reg.src_idx], tgt.points[reg.tgt_idx],
                                src.points[c[:, 0]], tgt.points[c[:, 1]], rc.ransac.distance)
        out[ranking] = (ok, kind)
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, dict[str, Tally]]:
    p = argparse.ArgumentParser(prog="python -m pcrcg.benchmarks.ranking", description=__doc__.split("\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("--root", default="data/synthmatch-cpu")
    p.add_argument("--benchmarks", nargs="+", default=["3DMatch", "3DLoMatch"])
    p.add_argument("--pairs", type=int, default=100, help="pairs per benchmark (spread evenly; counted ones kept)")
    p.add_argument("--n-points", type=int, default=5000)
    p.add_argument("--profile", default="cpu", help="the profile whose registration settings apply")
    p.add_argument("--distance", type=float, default=None, help="RANSAC distance, m (default: the profile's)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    if args.pairs < 1 or args.n_points < 3:
        p.error(f"--pairs must be >= 1 and --n-points >= 3, got {args.pairs} and {args.n_points}")
    if not Path(args.checkpoint).is_file():
        p.error(f"checkpoint not found: {args.checkpoint}")
    missing = [b for b in args.benchmarks if not (Path(args.root) / "benchmarks" / b).is_dir()]
    if missing:
        p.error(f"no benchmark folder {Path(args.root) / 'benchmarks' / missing[0]} (--root, --benchmarks)")

    import torch
    from tqdm import tqdm

    from pcrcg.data.stats.collect import evaluate_config
    from pcrcg.evaluation.metrics import counted_mask, load_benchmark
    from pcrcg.evaluation.model import as_fragment
    from pcrcg.evaluation.stage import configs_from
    from pcrcg.models.train import infer, load_module
    from pcrcg.registration.feature_registration import pair_seed

    torch.set_num_threads(1)
    cfg, _ = configs_from(evaluate_config(args.profile), device="cpu")
    ransac = cfg.ransac if args.distance is None else dataclasses.replace(cfg.ransac, distance=args.distance)
    cfg = dataclasses.replace(cfg, n_points=(args.n_points,), ransac=ransac)
    module = load_module(args.checkpoint, "cpu")
    tallies: dict[str, dict[str, Tally]] = {}
    for bench in args.benchmarks:
        gt = load_benchmark(Path(args.root) / "benchmarks" / bench)
        look = {(s, pr.i, pr.j): (g.transforms[k], g.infos[k]) for s, g in gt.items()  # the pairs recall counts
                for k, (pr, counted) in enumerate(zip(g.pairs, counted_mask(g.pairs))) if counted}
        tallies[bench] = {r: Tally() for r in RANKINGS}
        outputs = infer(module, args.root, bench, max_pairs=args.pairs, progress=False)
        for out in tqdm(outputs, desc=f"rank {bench}", total=args.pairs, unit="pair"):
            s, i, j = str(out.scene), int(out.i), int(out.j)
            if (s, i, j) not in look:
                continue
            T_gt, info = look[(s, i, j)]
            res = diagnose_pair(as_fragment(out.src), as_fragment(out.tgt), T_gt, info, args.n_points, cfg,
                                pair_seed(args.seed, s, i, j, args.n_points))
            for r, (ok, kind) in res.items():
                tallies[bench][r].add(ok, kind)
    print(f"\n{args.checkpoint}: N = {args.n_points}, RANSAC distance {cfg.ransac.distance:g} m, {cfg.ransac.budget}; "
          f"counted pairs of {args.pairs} spread per benchmark")
    print(f"{'benchmark':<10} {'ranking':<16} {'pairs':>5} {'RR %':>7} {'failed':>6} {'ranking':>8} {'search':>7}")
    for bench, by in tallies.items():
        for r, t in by.items():
            print(t.row(bench, r))
    print("ranking: the chosen pose scores at least as high as the ground truth under the ranking that chose it "
          "(a larger budget cannot help); search: the ground truth scores higher")
    return tallies


if __name__ == "__main__":
    main()
