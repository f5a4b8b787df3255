"""Is the overlap head what limits a model? Its scores against the truth, and registration with perfect ones.

    python -m pcrcg.benchmarks.overlap CHECKPOINT [--root data/synthmatch-cpu] [--benchmark 3DLoMatch]
        [--pairs 150] [--radius 1.5] [--distance 2.0]

On ``--pairs`` pairs of a test benchmark (spread evenly), from the model's outputs:

* **AUC** of the overlap scores (and of the matchability scores) against the true overlap labels (a
  point is in the overlap when the other fragment has a point within ``--radius`` voxels after the
  ground-truth motion); 0.5 is chance. Also the overlap AUC of the same source fragment run against
  an unrelated partner (a fragment of another scene): if it stays the same, the head does not use
  the other fragment, which is what Predator's overlap attention is for.
* **Registration recall** at N = 5000 / 1000 / 250 (the run's protocol: Open3D 0.10's RANSAC budget,
  ``--distance`` voxels) with the points sampled by the model's overlap x matchability, by the true
  overlap (an oracle: what a perfect overlap head would give with the same descriptors), by the overlap
  head alone (matchability left out: its loss is gated on the descriptors' hit rate), uniformly, and
  by two scores read off the descriptors alone (no head; their AUCs too): each point's best cosine
  similarity to the other fragment, and Lowe's ratio of its two nearest descriptors there.

* **Single-fragment cues**: the AUC against the truth of what one fragment alone tells (distance to its
  centroid, height and range in its camera frame) and their rank correlation with the head's scores. A
  head that follows such a cue does not need the other fragment; one whose cue reverses between
  generated and real data (``--root data/real-redkitchen``) has learned a shortcut of the generator.

For models with per-point overlap scores (Predator). Prints figures; asserts nothing.

Measured 2026-12-03 (cpu profile, seed 0, 150 + 150 test pairs of generator v6, 149 / 138 counted; RR at
N = 5000 / 1000 / 250), geometry-only Predator then implicit RGB (``features=rgb projection=implicit``):

* 3DLoMatch overlap AUC 0.568 (0.559 with an unrelated partner) / 0.590; descriptor-similarity AUC 0.547 /
  0.640; RR with the model's scores 1.1 / 3.0 / 3.1 and 4.0 / 9.0 / 9.9, with the true overlap 1.1 / 56.6
  / 87.2 and 4.0 / 61.4 / 87.4, uniform 1.1 / 1.1 / 1.1 and 4.0 / 4.1 / 3.5; the descriptor scores
  sample no better than uniformly (RGB: 4.0 / 5.1 / 2.3 at best). At N = 5000 (about every point) even
  the true overlap registers 1-4%: 1,000 validated hypotheses are too few at these inlier ratios.
* 3DMatch overlap AUC 0.660 (0.638) / 0.686; RR with the model's scores 70.1 / 72.2 / 70.0 and 75.0 /
  77.2 / 74.6, with the true overlap 70.1 / 96.0 / 100.0 and 75.0 / 96.4 / 100.0, uniform 70.1 / 76.2 /
  70.2 and 75.0 / 75.0 / 72.0 (the heads' sampling is no better than uniform here); the descriptor
  scores within 2.5 points of uniform.

The descriptors are good enough (what a perfect overlap head would give them); the overlap head is
not, and it barely reads the other fragment (an unrelated partner costs 0.01 AUC).

The same geometry model on the real redkitchen scene (``--root data/real-redkitchen``; 10 3DLoMatch and
18 counted 3DMatch pairs): overlap AUC 0.459 and 0.536, RR with the true overlap 70 / 90 (3DLoMatch, N =
1000 / 250) and 100 / 100 (3DMatch; FPFH + RANSAC: 88.9), with the head's scores 10 / 10 and 72.2 / 72.2.
Its head follows the points' height in the camera frame (rank correlation +0.38 generated, +0.41 real),
a cue that predicts the overlap on generated 3DLoMatch (AUC 0.582) and the reverse on the real pairs
(0.368): a shortcut of the generator (40 generated / 10 real 3DLoMatch pairs, 2026-12-03).
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any, Sequence

import numpy as np


def overlap_labels(src_points: np.ndarray, tgt_points: np.ndarray, transform: np.ndarray,
                   radius: float) -> tuple[np.ndarray, np.ndarray]:
    """True overlap of a pair: src (N, 3), tgt (M, 3) in their own frames, transform (4, 4) src -> tgt ->
    (N,) and (M,) bool (a point of one fragment within ``radius`` of a point of the other)."""
    from scipy.spatial import cKDTree

    from pcrcg.geometry import transform_points

    s = transform_points(np.asarray(transform, np.float64), np.asarray(src_points, np.float64))
    t = np.asarray(tgt_points, np.float64)
    return cKDTree(t).query(s)[0] < radius, cKDTree(s).query(t)[0] < radius


def auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve of scores (N,) for bool labels (N,) (ties count half); nan with one class."""
    labels = np.asarray(labels, bool)
    pos, neg = int(labels.sum()), int((~labels).sum())
    if pos == 0 or neg == 0:
        return float("nan")
    from scipy.stats import rankdata

    ranks = rankdata(np.asarray(scores, np.float64))
    return float((ranks[labels].sum() - pos * (pos + 1) / 2) / (pos * neg))


def with_scores(out: Any, src_overlap: np.ndarray, tgt_overlap: np.ndarray, floor: float = 1e-3) -> Any:
    """A copy of a pair's outputs whose overlap scores are the given ones (at least ``floor``) and whose
    matchability is 1: the sampling then follows these scores alone."""
    from pcrcg.registration.feature_registration import FragmentOutput

    def frag(f, ov):  # noqa: ANN001, ANN202
        ov = np.maximum(np.asarray(ov, np.float32), floor)
        return FragmentOutput(f.points, f.descriptors, ov, np.ones_like(ov))

    return dataclasses.replace(out, src=frag(out.src, src_overlap), tgt=frag(out.tgt, tgt_overlap))


def mean_auc(scores: Sequence[tuple[np.ndarray, np.ndarray]], labels: Sequence[tuple[np.ndarray, np.ndarray]]) -> float:
    """Mean :func:`auc` over the pairs' two fragments: scores and labels, per pair, (N,) and (M,) arrays."""
    return float(np.nanmean([auc(sc, lb) for sp, lp in zip(scores, labels) for sc, lb in zip(sp, lp)]))


def score_heads(outs: Sequence[Any], labels: Sequence[tuple[np.ndarray, np.ndarray]],
                module: Any = None) -> dict[str, float]:
    """Mean AUCs of the overlap and matchability scores over the pairs (both fragments), given each pair's
    true overlap ``labels`` (:func:`overlap_labels`); with ``module`` (geometry only), also the source's
    overlap AUC when run against another scene's target fragment."""
    from scipy.spatial import cKDTree

    from pcrcg.models.train import infer_clouds

    swapped = []
    for k, (o, (ls, _)) in enumerate(zip(outs, labels)):
        other = next((x for x in list(outs[k + 1:]) + list(outs[:k]) if x.scene != o.scene), None)
        # a color model needs the partner's views, which the outputs do not carry: no swapped row for it
        if module is not None and other is not None and getattr(module, "lifter", None) is None:
            sw = infer_clouds(module, o.src.points, other.tgt.points)
            nearest = cKDTree(o.src.points).query(sw.src.points)[1]  # the run re-voxelises: label by nearest point
            swapped.append(auc(sw.src.overlap, ls[nearest]))
    res = {"overlap_auc": mean_auc([(o.src.overlap, o.tgt.overlap) for o in outs], labels),
           "matchability_auc": mean_auc([(o.src.matchability, o.tgt.matchability) for o in outs], labels)}
    if swapped:
        res["overlap_auc_unrelated_partner"] = float(np.nanmean(swapped))
    return res


def descriptor_agreement(src_desc: np.ndarray, tgt_desc: np.ndarray, chunk: int = 2048) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Scores of "has a partner in the other fragment" read off the descriptors alone (no head): src_desc
    (N, D), tgt_desc (M, D), unit norm -> {"similarity": best cosine similarity to the other fragment
    mapped to [0, 1], "ratio": 1 - d1 / d2 of the two nearest descriptors (Lowe's ratio, 0 when the two
    are as near)}, each a pair of arrays (N,), (M,)."""

    def one_way(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sim, ratio = np.zeros(len(a), np.float32), np.zeros(len(a), np.float32)
        if len(b) < 2:
            return sim, ratio
        for k in range(0, len(a), chunk):
            s = a[k:k + chunk] @ b.T  # (n, M)
            top = -np.partition(-s, 1, axis=1)[:, :2]  # the two best similarities, unordered
            s1, s2 = top.max(1), top.min(1)
            d1 = np.sqrt(np.clip(2.0 - 2.0 * s1, 0.0, None))
            d2 = np.sqrt(np.clip(2.0 - 2.0 * s2, 1e-12, None))
            sim[k:k + chunk] = (1.0 + s1) / 2.0
            ratio[k:k + chunk] = 1.0 - d1 / d2
        return sim, ratio

    a, b = np.asarray(src_desc, np.float32), np.asarray(tgt_desc, np.float32)
    (ss, sr), (ts, tr) = one_way(a, b), one_way(b, a)
    return {"similarity": (ss, ts), "ratio": (sr, tr)}


def single_fragment_cues(points: np.ndarray) -> dict[str, np.ndarray]:
    """Cues a head could read off one fragment alone, in its own frame (the camera frame of its first
    frame: x right, y down, z forward): points (N, 3) -> {"periphery": distance to the fragment's
    centroid, "camera y (down)": y, "range": distance to the camera, "depth": z}, each (N,) float64.
    A head that follows one of them does not need the other fragment; one whose sign flips between
    data sets (generated and real) is a shortcut."""
    p = np.asarray(points, np.float64)
    return {"periphery": np.linalg.norm(p - p.mean(0), axis=1), "camera y (down)": p[:, 1],
            "range": np.linalg.norm(p, axis=1), "depth": p[:, 2]}


def cue_table(outs: Sequence[Any], labels: Sequence[tuple[np.ndarray, np.ndarray]]) -> dict[str, tuple[float, float]]:
    """Per cue of :func:`single_fragment_cues`: (mean AUC of the cue against the true overlap, mean Spearman
    rank correlation of the cue with the overlap head's scores) over the pairs' fragments."""
    from scipy.stats import spearmanr

    aucs: dict[str, list[float]] = {}
    corrs: dict[str, list[float]] = {}
    for o, pair_labels in zip(outs, labels):
        for f, lab in zip((o.src, o.tgt), pair_labels):
            for name, cue in single_fragment_cues(f.points).items():
                aucs.setdefault(name, []).append(auc(cue, lab))
                flat = np.ptp(cue) == 0 or np.ptp(f.overlap) == 0
                corrs.setdefault(name, []).append(float("nan") if flat else float(spearmanr(cue, f.overlap)[0]))
    return {n: (float(np.nanmean(aucs[n])), float(np.nanmean(corrs[n]))) for n in aucs}


def sampling_variants(outs: Sequence[Any], radius: float,
                      labels: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
                      agreement: Sequence[dict[str, tuple[np.ndarray, np.ndarray]]] | None = None) -> dict[str, list]:
    """The pairs' outputs as the model gives them, with the overlap head's scores alone (matchability 1),
    with the true overlap as scores (``labels``, or computed within ``radius``), with flat scores, and (given ``agreement``, :func:`descriptor_agreement` per pair)
    with each descriptor score in place of the heads'."""
    if labels is None:
        labels = [overlap_labels(o.src.points, o.tgt.points, o.transform, radius) for o in outs]
    oracle = [with_scores(o, ls, lt) for o, (ls, lt) in zip(outs, labels)]
    flat = [with_scores(o, np.ones(len(ls)), np.ones(len(lt))) for o, (ls, lt) in zip(outs, labels)]
    overlap_only = [with_scores(o, o.src.overlap, o.tgt.overlap) for o in outs]
    res = {"model": list(outs), "overlap head alone": overlap_only, "true overlap (oracle)": oracle, "uniform": flat}
    for name in (agreement[0] if agreement else {}):
        res[f"descriptor {name}"] = [with_scores(o, *ag[name]) for o, ag in zip(outs, agreement)]
    return res


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m pcrcg.benchmarks.overlap", description=__doc__.split("\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("--root", default="data/synthmatch-cpu")
    p.add_argument("--benchmark", default="3DLoMatch", choices=["3DMatch", "3DLoMatch"])
    p.add_argument("--pairs", type=int, default=150, help="pairs of the benchmark (spread evenly)")
    p.add_argument("--radius", type=float, default=1.5, help="overlap label radius, in voxels of the model")
    p.add_argument("--distance", type=float, default=2.0, help="RANSAC distance, in voxels of the model")
    p.add_argument("--n-points", type=int, nargs="+", default=[5000, 1000, 250])
    args = p.parse_args(argv)

    import torch

    from pcrcg.evaluation.model import evaluate_model_outputs
    from pcrcg.models.train import infer, load_module
    from pcrcg.registration.feature_registration import RegistrationConfig
    from pcrcg.registration.ransac import RansacConfig

    torch.set_num_threads(1)
    module = load_module(args.checkpoint, "cpu")
    voxel = float(module.hparams["model"]["voxel_size"])
    outs = list(infer(module, args.root, args.benchmark, max_pairs=args.pairs, progress=True))
    radius = args.radius * voxel
    labels = [overlap_labels(o.src.points, o.tgt.points, o.transform, radius) for o in outs]
    heads = score_heads(outs, labels, module)
    agreement = [descriptor_agreement(o.src.descriptors, o.tgt.descriptors) for o in outs]
    for name in agreement[0]:
        heads[f"descriptor_{name}_auc"] = mean_auc([ag[name] for ag in agreement], labels)
    print(f"{len(outs)} pairs of {args.root} {args.benchmark}; overlap labels within {radius:.3f} m")
    unrelated = heads.get("overlap_auc_unrelated_partner")
    why_not = "n/a: a color model" if getattr(module, "lifter", None) is not None else "n/a: one scene"
    print(f"overlap AUC {heads['overlap_auc']:.3f} (with an unrelated partner: "
          f"{why_not if unrelated is None else f'{unrelated:.3f}'}); matchability AUC {heads['matchability_auc']:.3f}")
    print("AUC of the descriptors' own agreement (no head): "
          + "; ".join(f"{n} {heads[f'descriptor_{n}_auc']:.3f}" for n in agreement[0]))
    cues = cue_table(outs, labels)
    print("single-fragment cues (AUC against the truth; rank correlation with the overlap head): "
          + "; ".join(f"{n} {a:.3f} ({c:+.2f})" for n, (a, c) in cues.items()))
    cfg = RegistrationConfig(fewer_points="with_replacement", n_points=tuple(args.n_points),
                             ransac=RansacConfig(distance=args.distance * voxel, max_validation=1000, confidence=1.0))
    bench = f"{args.root}/benchmarks/{args.benchmark}"
    print("sampled by                 " + " ".join(f"RR@{n:<5}" for n in args.n_points) + " counted")
    rows = {}
    for name, variant in sampling_variants(outs, radius, labels, agreement).items():
        m = evaluate_model_outputs(variant, bench, cfg=cfg, only_evaluated=True, progress=False)
        rows[name] = {n: m[f"rr_{n}"] for n in args.n_points}
        print(f"{name:26s} " + " ".join(f"{m[f'rr_{n}']:7.1f}" for n in args.n_points) + f" {m['n_counted']:7.0f}")
    return {"heads": heads, "cues": cues, "rr": rows}


if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.benchmarks.overlap"):  # a bad file or setting: one line, exit 2
        main()
