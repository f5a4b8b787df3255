"""A stand-in stage for the reliability tests (no tests here): real Lightning training that marks its
steps and goes slowly enough to be interrupted."""

from __future__ import annotations

import time
from pathlib import Path

from lightning.pytorch.callbacks import Callback

from pcrcg.pipeline import RunContext, TrainOutput


class _Marker(Callback):
    """Writes ``<base>/training_step.txt`` (one line per step, "<seed> <step>") before each training
    step and waits ``delay`` seconds after it."""

    def __init__(self, path: Path, seed: int, delay: float):
        self.path, self.seed, self.delay = path, seed, delay

    def on_train_batch_start(self, trainer, *args) -> None:  # noqa: ANN001
        with open(self.path, "a") as f:
            f.write(f"{self.seed} {trainer.global_step}\n")

    def on_train_batch_end(self, trainer, *args) -> None:  # noqa: ANN001
        time.sleep(self.delay)


def slow_train(ctx: RunContext) -> TrainOutput:
    """The models stage's real training (Lightning), in ``paths.checkpoints/seed<k>`` so that a
    relaunch resumes from ``last.ckpt``, with :class:`_Marker` watching the steps."""
    from pcrcg.models.train import train

    seed = int(ctx.cfg.seed)
    out = ctx.path("checkpoints") / f"seed{seed}"
    res = train(ctx.cfg, data_root=ctx.data_root, out_dir=out, logger=False, device="cpu",
                callbacks=[_Marker(ctx.job.base_dir / "training_step.txt", seed, 0.5)])
    return TrainOutput(checkpoint=Path(res["checkpoint"]), history=res["history"], metrics=res["metrics"])
