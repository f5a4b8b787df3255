"""What MLflow tracking adds to a run: ``python -m pcrcg.benchmarks.tracking [--runs 5]``.

Runs the real pipeline (:func:`pcrcg.pipeline.run_job`) with no-op stages that return a full
set of metrics (2 benchmarks x 5 sample sizes x RR/FMR/IR + RRE/RTE + coverage), a 3-point
training curve, a checkpoint and an ``est.log`` per benchmark, first with ``logger=none``,
then with ``logger=mlflow`` into a fresh SQLite store, and prints the time per run of each
and the difference: the overhead of tracking. It also prints the one-time costs (importing
mlflow, creating the store) and the time of a skipped job (config hash already FINISHED).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from pcrcg.config import CONF_DIR, load_run_config
from pcrcg.pipeline import EvalOutput, JobInfo, RunContext, TrainOutput, run_job

def noop_prepare(ctx: RunContext) -> Path:
    return ctx.out_dir


def noop_train(ctx: RunContext) -> TrainOutput:
    ckpt = ctx.out_dir / "model.ckpt"
    ckpt.write_bytes(b"\0" * 1024 * 1024)  # 1 MiB
    return TrainOutput(checkpoint=ckpt, history={"train/loss": [1.0, 0.5, 0.25]})


def noop_evaluate(ctx: RunContext) -> EvalOutput:
    metrics = {}
    arts = []
    for b in ("3DMatch", "3DLoMatch"):
        for n in (5000, 2500, 1000, 500, 250):
            for m in ("rr", "fmr", "ir"):
                metrics[f"{b}/{m}_{n}"] = 50.0
        metrics[f"{b}/rre"], metrics[f"{b}/rte"] = 2.0, 0.07
        est = ctx.out_dir / "est" / b / "scene" / "est.log"
        est.parent.mkdir(parents=True, exist_ok=True)
        est.write_text("0 2 3\n" + "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
        arts.append((est.parent.parent, f"est_logs/{b}"))
    metrics["color_coverage"] = 0.8
    return EvalOutput(metrics, arts, {"3DMatch": {"n_pairs": 1623}, "3DLoMatch": {"n_pairs": 1781}})


def _time_runs(conf: Path, tmp: Path, logger: str, n: int, tag: str) -> list[float]:
    times = []
    for i in range(n):
        cfg = load_run_config([f"logger={logger}", "profile=tiny", f"seed={i}", f"experiment_name=bench_{tag}",
                               "stages.prepare=pcrcg.benchmarks.tracking.noop_prepare",
                               "stages.train=pcrcg.benchmarks.tracking.noop_train",
                               "stages.evaluate=pcrcg.benchmarks.tracking.noop_evaluate",
                               "runtime.reuse_checkpoints=false"], conf)
        job = JobInfo(output_dir=tmp / f"{tag}_{logger}_{i}", base_dir=tmp, overrides=[f"seed={i}"],
                      multirun=True, search_dirs=(conf,))
        t = time.perf_counter()
        out = run_job(cfg, job)
        times.append(time.perf_counter() - t)
        assert out.status == "finished", out
    return times


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args(argv)
    import os

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        conf = CONF_DIR
        os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{tmp}/mlflow.db"
        # warm imports shared by both modes (hydra, omegaconf, matplotlib for the per-run plot)
        _time_runs(conf, tmp, "none", 1, "warm")
        t = time.perf_counter()
        import mlflow  # noqa: F401

        t_import = time.perf_counter() - t
        from pcrcg.tracking.store import ensure_store

        t = time.perf_counter()
        ensure_store(os.environ["MLFLOW_TRACKING_URI"])
        t_store = time.perf_counter() - t
        plain = _time_runs(conf, tmp, "none", args.runs, "a")
        tracked = _time_runs(conf, tmp, "mlflow", args.runs, "b")
        # a relaunch: the same configs are now FINISHED -> skipped
        t = time.perf_counter()
        cfg = load_run_config(["profile=tiny", "seed=0", "experiment_name=bench_b",
                               "stages.prepare=pcrcg.benchmarks.tracking.noop_prepare",
                               "stages.train=pcrcg.benchmarks.tracking.noop_train",
                               "stages.evaluate=pcrcg.benchmarks.tracking.noop_evaluate",
                               "runtime.reuse_checkpoints=false"], conf)
        t_compose = time.perf_counter() - t
        t = time.perf_counter()
        out = run_job(cfg, JobInfo(output_dir=tmp / "skip", base_dir=tmp, overrides=["seed=0"], multirun=True,
                                   search_dirs=(conf,)))
        t_skip = time.perf_counter() - t
        assert out.status == "skipped", out

    from pcrcg.tracking.hashing import flat_params

    n_params = len(flat_params(cfg)) + 2
    med = statistics.median
    print()
    print(f"tracking overhead per run (median of {args.runs}; no-op stages; {n_params} params, 39 metrics, "
          f"a 3-step curve, 1 MiB checkpoint, 2 est.log folders, config files, plot)")
    print(f"  logger=none    {med(plain):6.3f} s/run   (validate, hash, outputs, per-run plot)")
    print(f"  logger=mlflow  {med(tracked):6.3f} s/run")
    print(f"  overhead       {med(tracked) - med(plain):6.3f} s/run")
    print(f"  skipped job    {t_skip:6.3f} s       (lookup of a FINISHED run with the same config hash)")
    print("one-time costs per process")
    print(f"  import mlflow  {t_import:6.3f} s")
    print(f"  new store      {t_store:6.3f} s       (SQLite schema; done once by the multirun callback)")
    print(f"  compose config {t_compose:6.3f} s       (Hydra, for reference)")
    sys.stdout.flush()


if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.benchmarks.tracking"):  # a bad file or setting: one line, exit 2
        main()
