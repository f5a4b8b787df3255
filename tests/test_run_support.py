"""Helpers for the orchestration tests (no tests here): a config tree, fake stages, a CLI runner.

The fake stages stand in for data generation, training and evaluation: they return metrics
computed from the config (so tests know every number), write est.log files and a checkpoint,
count how often training ran, and fail on demand (``PCRCG_FAKE_FAIL="window_size=17"``).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
from pathlib import Path
from typing import Sequence

from omegaconf import OmegaConf

from pcrcg.config import CONF_DIR
from pcrcg.pipeline import EvalOutput, RunContext, TrainOutput

FAKES = [
    "stages.prepare=test_run_support.fake_prepare",
    "stages.train=test_run_support.fake_train",
    "stages.evaluate=test_run_support.fake_evaluate",
]
N_POINTS = (5000, 2500, 1000, 500, 250)


def make_conf(dst: Path) -> Path:
    """A copy of conf/ at ``dst`` (tests may add files to it); a missing option file fails the tests."""
    shutil.copytree(CONF_DIR, dst)
    return dst


# --------------------------------------------------------------------------- fake stages


def _counter(ctx: RunContext, name: str) -> None:
    with open(ctx.job.base_dir / f"{name}_calls.txt", "a") as f:
        f.write(f"{ctx.cfg.experiment_name} {ctx.out_dir.name}\n")


def _maybe_fail(ctx: RunContext, stage: str) -> None:
    spec = os.environ.get("PCRCG_FAKE_FAIL", "")
    if spec:
        key, value = spec.split("=", 1)
        if str(OmegaConf.select(ctx.cfg, key)) == value:
            raise RuntimeError(f"fake {stage} failure for {spec}")


def fake_prepare(ctx: RunContext) -> Path:
    root = ctx.path("data") / "fake"
    root.mkdir(parents=True, exist_ok=True)
    return root


def fake_train(ctx: RunContext) -> TrainOutput:
    _counter(ctx, "train")
    ckpt = ctx.out_dir / "train" / "model.ckpt"
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    ckpt.write_bytes(b"fake weights")
    return TrainOutput(checkpoint=ckpt, history={"train/loss": [1.0, 0.5, 0.25], "val/loss": [(0, 1.2), (2, 0.6)]})


def resumed_train(ctx: RunContext) -> TrainOutput:
    """:func:`fake_train`, as a training resumed from a checkpoint says so: the earlier starts' seconds."""
    out = fake_train(ctx)
    out.metrics = {"train/resumed_from_step": 5.0, "time/train_earlier_s": 400.0, "time/train_earlier_cpu_s": 300.0}
    return out


def threads_evaluate(ctx: RunContext) -> EvalOutput:
    """:func:`fake_evaluate`, after writing the torch CPU threads it runs with and the native pools' (OpenBLAS,
    OpenMP: :func:`native_threads`) to ``eval_threads.txt``."""
    import torch

    with open(ctx.job.base_dir / "eval_threads.txt", "a") as f:
        f.write(f"{torch.get_num_threads()} {native_threads()}\n")
    return fake_evaluate(ctx)


def native_threads() -> str:
    """The threads of every native pool loaded in this process (OpenBLAS, OpenMP, ...), distinct values joined."""
    from threadpoolctl import threadpool_info

    return ",".join(str(v) for v in sorted({int(p["num_threads"]) for p in threadpool_info()}))


def expected_rr(window_size: int, seed: int, n: int, benchmark: str) -> float:
    """The recall the fake evaluation reports (%): known to the tests."""
    base = 80.0 if benchmark == "3DMatch" else 50.0
    return base + window_size - 2.0 * math.log10(5000 / n) + 0.5 * seed


def fake_evaluate(ctx: RunContext) -> EvalOutput:
    _counter(ctx, "evaluate")
    _maybe_fail(ctx, "evaluate")
    ws, seed = int(ctx.cfg.window_size), int(ctx.cfg.seed)
    metrics: dict[str, float] = {}
    artifacts = []
    for bench in ctx.cfg.eval.benchmarks:
        for n in N_POINTS:  # all five, whatever the profile evaluates
            metrics[f"{bench}/rr_{n}"] = expected_rr(ws, seed, n, bench)
            metrics[f"{bench}/fmr_{n}"] = 90.0
            metrics[f"{bench}/ir_{n}"] = 30.0
        metrics[f"{bench}/rr"] = expected_rr(ws, seed, 5000, bench)
        metrics[f"{bench}/rre"] = 2.0
        metrics[f"{bench}/rte"] = 0.07
        est = ctx.out_dir / "eval" / bench / "scene-a" / "est.log"
        est.parent.mkdir(parents=True, exist_ok=True)
        est.write_text("0 2 3\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
        artifacts.append((est.parent.parent, f"est_logs/{bench}"))
    metrics["color_coverage"] = min(1.0, 0.3 * int(ctx.cfg.views))
    protocol = {b: {"n_pairs": 12, "n_pairs_rr": 9} for b in ctx.cfg.eval.benchmarks}
    protocol["ransac"] = {"iterations": int(ctx.cfg.eval.ransac_iterations), "distance": 0.05}
    return EvalOutput(metrics=metrics, artifacts=artifacts, protocol=protocol)


# --------------------------------------------------------------------------- running the CLI in-process


def stand_in_pri3d(root: Path) -> Path:
    """A stand-in torch file where the tiny profile's ``encoder2d=pri3d`` looks for its weights under ``root``
    (the window_size experiment runs with Pri3D weights, its caption's; the fake stages never read them, the
    preflight reads every weights file named)."""
    import torch

    path = root / "checkpoints" / "pretrain2d" / "synthmatch-seed1-tiny" / "pri3d_resnet18.pth"
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"stand-in": torch.zeros(1)}, path)
    return path


def run_cli(args: Sequence[str], cwd: Path, monkeypatch) -> int:
    """``python -m pcrcg.run <args>`` inside this process (cwd = ``cwd``); returns the exit code."""
    from pcrcg import run as run_mod

    monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "argv", ["pcrcg.run", *args])
    try:
        run_mod.main()
    except SystemExit as e:
        return int(e.code or 0)
    return 0


def tracked_runs(uri: str, experiment: str):
    from mlflow.tracking import MlflowClient

    c = MlflowClient(uri)
    exp = c.get_experiment_by_name(experiment)
    return [] if exp is None else c.search_runs([exp.experiment_id], max_results=1000)


def read_status_files(root: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(root.rglob("pcrcg_status.json"))]
