"""Evaluation speed, before and after the exact shortcuts, side by side (prints figures; asserts nothing).

    python -m pcrcg.benchmarks.evaluation CHECKPOINT [--root data/synthmatch-cpu] [--pairs 10]
        [--distance 0.12]

For a model with deep 2D features, inference first: seconds per pair with the 2D encoder run on every
pair's views (before) and with each view's map computed once and reused (after,
:meth:`pcrcg.vision.features.FeatureExtractor.frozen_maps`), and whether the outputs are identical. Then,
per N of the protocol, seconds per pair of registration (sampling, matching, RANSAC) on a trained model's
outputs for ``--pairs`` pairs of each test benchmark, with the run's default budget (Open3D 0.10's
``(50000, 1000)``) and with ``registration=early_exit``:

* **before**: every sampled row matched (no ``src_ids``/``tgt_ids``) in blocks of 4,096 rows and
  ``RansacConfig(prune=False)``
  (every point of every validated hypothesis scored);
* **after**: the defaults (each distinct sampled point matched once, in blocks of
  ``pcrcg.registration.matching.CPU_CHUNK`` rows on CPU; the voxel-grid overlap scorer,
  ``pcrcg.registration.ransac._GridOverlapScore``, which decides most points without the KD-tree and
  drops hypotheses that can no longer win).

It also says whether both gave the same transforms, correspondences and RANSAC counts on every pair.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pcrcg.config import N_POINTS


def infer_outputs(module, root: str, pairs: int, memo_bytes: int | None = None) -> tuple[list, float, float]:
    """The model's outputs on the first ``pairs`` pairs of each test benchmark of ``root`` and the wall and
    process CPU seconds per pair (data + network). For a deep-feature model the 2D maps are reused up to ``memo_bytes`` (0: computed
    on every pair's views; None: the default bound), from an empty memo."""
    import itertools

    from pcrcg.models.train import infer

    extractor = module.lifter.extractor if module.lifter is not None else None
    if getattr(extractor, "kind", None) == "deep":
        extractor.memo_bytes = memo_bytes
        extractor._deep_memo.clear()  # a new bound starts from an empty memo
    got, t0, c0 = [], time.perf_counter(), time.process_time()
    for b in ("3DMatch", "3DLoMatch"):
        got += list(itertools.islice(infer(module, root, b, max_pairs=pairs, progress=False), pairs))
    n = max(len(got), 1)
    return got, (time.perf_counter() - t0) / n, (time.process_time() - c0) / n


# the two budgets timed: the run's default (Open3D 0.10) and registration=early_exit
BUDGETS = (("run default: Open3D 0.10 budget (50000, 1000)", 1000, 1.0), ("registration=early_exit", None, 0.999))


def registration_speed(outs: list, distance: float, max_validation: int | None = 1000, confidence: float = 1.0,
                       score: str = "overlap") -> dict:
    """Seconds per pair of registration (sampling, matching, RANSAC) at every N of the protocol on the
    outputs ``outs`` (:func:`infer_outputs`), before (every sampled row matched, no pruning) and after (the
    defaults): ``{"before": {N: s}, "after": {N: s}, "before_cpu": {N: s}, "after_cpu": {N: s}, "identical":
    bool}`` (wall, and this process's CPU seconds, steadier on a shared machine; identical: same transforms,
    correspondences and RANSAC counts on every pair and N)."""
    import pcrcg.registration.feature_registration as P
    from pcrcg.evaluation.model import as_fragment
    from pcrcg.registration.feature_registration import RegistrationConfig, pair_seed, register_features
    from pcrcg.registration.ransac import RansacConfig

    plain = P.match_descriptors

    def match_every_row(a, b, src_ids=None, tgt_ids=None, chunk=None, **kw):  # noqa: ANN001, ARG001
        return plain(a, b, chunk=4096, **kw)

    seconds, results = {}, {}
    for new in (False, True):
        P.match_descriptors = plain if new else match_every_row
        try:
            cfg = RegistrationConfig(fewer_points="with_replacement", ransac=RansacConfig(
                distance=distance, max_validation=max_validation, confidence=confidence, prune=new, score=score))
            per_n, cpu_n, res = {}, {}, []
            for n in N_POINTS:
                t, c = time.perf_counter(), time.process_time()
                for o in outs:
                    r = register_features(as_fragment(o.src), as_fragment(o.tgt), n, cfg,
                                          seed=pair_seed(0, o.scene, o.i, o.j, n))
                    res.append((r.transform, r.correspondences, r.ransac.iterations, r.ransac.n_checked))
                per_n[n] = (time.perf_counter() - t) / len(outs)
                cpu_n[n] = (time.process_time() - c) / len(outs)
        finally:
            P.match_descriptors = plain
        tag = "after" if new else "before"
        seconds[tag], seconds[f"{tag}_cpu"], results[new] = per_n, cpu_n, res
    same = all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2:] == b[2:]
               for a, b in zip(results[False], results[True]))
    return {**seconds, "identical": bool(same)}


def print_registration(name: str, got: dict) -> None:
    """The per-N table of :func:`registration_speed`'s result."""
    print(f"\n{name}; identical results: {got['identical']}")
    print("     N   before s/pair   after s/pair   speed-up   |   CPU before   CPU after   speed-up")
    for n in N_POINTS:
        b0, b1, c0, c1 = got["before"][n], got["after"][n], got["before_cpu"][n], got["after_cpu"][n]
        print(f"{n:6d} {b0:15.3f} {b1:14.3f} {b0 / b1:9.2f}x   | {c0:12.3f} {c1:11.3f} {c0 / c1:9.2f}x")
    s0, s1 = sum(got["before"].values()), sum(got["after"].values())
    c0, c1 = sum(got["before_cpu"].values()), sum(got["after_cpu"].values())
    print(f"  all {len(N_POINTS)} N: {s0:.3f} -> {s1:.3f} s/pair ({s0 / s1:.2f}x); CPU {c0:.3f} -> {c1:.3f} s/pair "
          f"({c0 / c1:.2f}x)")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m pcrcg.benchmarks.evaluation", description=__doc__.split("\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("--root", default="data/synthmatch-cpu")
    p.add_argument("--pairs", type=int, default=10, help="pairs per benchmark (spread evenly)")
    p.add_argument("--distance", type=float, default=0.12, help="RANSAC distance, m (the cpu profile's: 2x 6 cm)")
    args = p.parse_args(argv)

    from pcrcg.device import cpu_threads

    # one thread for torch and the native pools, as a cpu-profile run (trainer.num_threads: 1): with torch's alone
    # limited, the shortcuts' NumPy products ran OpenBLAS on both cores (2026-12-07: 0.265 s of wall for 0.488 s of
    # CPU per pair after, so the wall-time speed-up counted a second core that a run does not use)
    with cpu_threads(1):
        _main(args)


def _main(args: argparse.Namespace) -> None:
    from pcrcg.models.train import load_module

    module = load_module(args.checkpoint, "cpu")
    extractor = module.lifter.extractor if module.lifter is not None else None
    deep = getattr(extractor, "kind", None) == "deep"
    bound = extractor.memo_bytes if deep else None  # the checkpoint's encoder2d.memo_mb, else DEEP_MEMO_BYTES

    if deep:  # before: the 2D encoder on every pair's views; after: each view's map once (eval mode)
        before, t_before, _ = infer_outputs(module, args.root, args.pairs, 0)
    outs, t_after, _ = infer_outputs(module, args.root, args.pairs, bound)
    if deep:
        same = all(np.array_equal(getattr(a, f).descriptors, getattr(b, f).descriptors)
                   and np.array_equal(getattr(a, f).overlap, getattr(b, f).overlap)
                   for a, b in zip(before, outs) for f in ("src", "tgt"))
        print(f"inference (data + network), deep 2D maps computed per pair -> once per view: {t_before:.3f} -> "
              f"{t_after:.3f} s/pair ({t_before / t_after:.2f}x) over {len(outs)} pairs; identical outputs: {same}")
    else:
        print(f"inference (data + network): {t_after:.3f} s/pair over {len(outs)} pairs")

    for name, mv, conf in BUDGETS:
        print_registration(name, registration_speed(outs, args.distance, mv, conf))


if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.benchmarks.evaluation"):  # a bad file or setting: one line, exit 2
        main()
