"""Evaluation: the 3DMatch / 3DLoMatch protocol, and running methods over the benchmarks.

The protocol and where published implementations differ are documented in
:mod:`pcrcg.evaluation.metrics`.

Evaluating a learned model (what training / orchestration calls)
----------------------------------------------------------------
::

    evaluate_model_outputs(
        outputs,                  # iterable of per-pair outputs, one per gt.log pair (streamed)
        benchmark,                # <dir>/<scene>/gt.log|gt.info, or load_benchmark(<dir>)
        *,
        cfg=RegistrationConfig(), # sampling, mutual, backend, device, n_points, ransac
        est_dir=None,             # writes <est_dir>/<N>/<scene>/est.log for every N
        seed=0,                   # per-pair seeds derive from (seed, scene, i, j, N)
        predator_variant=False,   # Predator's script: the first pair of each scene never counts
        inlier_distance=0.1, fmr_threshold=0.05, rmse_threshold=0.2,
        only_evaluated=False,     # True: score only the pairs given (a max_pairs subset);
                                  # False: a pair without output is a registration failure
        progress=True,
    ) -> dict[str, float]

Each output has ``scene``, ``i``, ``j`` (the ``gt.log`` entry: source = fragment j, target =
fragment i), ``src`` and ``tgt`` with ``points (N, 3)``, ``descriptors (N, D)``, ``overlap (N,)``,
``matchability (N,)`` (each fragment in its own frame; any object with those attributes, e.g.
``pcrcg.models.module.PairOutput``), and optionally ``color_coverage``. The ground truth comes
from the benchmark files, not from the outputs.

Returned keys (recall, IR and FMR in %, RRE in degrees, RTE in metres), for every N in
``cfg.n_points``: ``rr_<N>`` (per scene, then mean over scenes), ``rr_pair_<N>`` (pooled),
``fmr_<N>``, ``fmr_pair_<N>``, ``ir_<N>``, ``rre_<N>``, ``rte_<N>``, ``seconds_per_pair_<N>``;
then ``rre`` and ``rte`` (at the largest N: mean over scenes of the per-scene median over
registered, non-adjacent pairs, as Predator reports), ``n_pairs``, ``n_counted``,
``n_evaluated`` and ``color_coverage`` (mean over pairs, when the outputs carry it).

Other entry points
------------------
* :func:`score_directories` ``(benchmark_dir, estimate_dir, predator_variant=False) ->
  BenchmarkScore`` (``.rr``, ``.rr_pair``, ``.scenes``, ``.rre``, ``.rte``, ``.to_dict()``).
* :func:`pcrcg.evaluation.stage.evaluate` ``(cfg, *, data_root, checkpoint, out_dir, device)``:
  the pipeline's evaluation stage (``python -m pcrcg.run``).
* :func:`pcrcg.evaluation.stage.run_classical` ``(method, root, benchmark, *, cfg, out_dir, init, ...)``.
* ``python -m pcrcg.evaluate mode=score|pair|benchmark`` (see ``pcrcg/evaluate.py``).
"""

from pcrcg.evaluation.metrics import (
    FMR_THRESHOLD,
    INLIER_DISTANCE,
    RMSE_THRESHOLD,
    BenchmarkScore,
    SceneGT,
    SceneScore,
    correspondence_metrics,
    counted_mask,
    feature_match_recall,
    information_matrix,
    inlier_ratio,
    load_benchmark,
    load_estimates,
    load_scene_gt,
    read_estimates,
    registration_error,
    rotation_error_deg,
    rotation_to_quaternion,
    score_benchmark,
    score_directories,
    score_scene,
    transformation_error,
    translation_error,
    write_estimates,
)
from pcrcg.evaluation.model import as_fragment, evaluate_model_outputs

__all__ = [
    "FMR_THRESHOLD", "INLIER_DISTANCE", "RMSE_THRESHOLD", "BenchmarkScore", "SceneGT", "SceneScore",
    "correspondence_metrics", "counted_mask", "feature_match_recall", "information_matrix", "inlier_ratio",
    "load_benchmark", "load_estimates", "load_scene_gt", "read_estimates", "registration_error",
    "rotation_error_deg", "rotation_to_quaternion", "score_benchmark", "score_directories", "score_scene",
    "transformation_error", "translation_error", "write_estimates", "as_fragment", "evaluate_model_outputs",
]
