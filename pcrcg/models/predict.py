"""The hook the evaluation stage looks for: per-pair network outputs on a test benchmark.

:func:`predict_benchmark` ``(cfg, data_root, checkpoint, benchmark, device="cpu", max_pairs=None)
-> Iterator[PairOutput]``: each :class:`~pcrcg.models.module.PairOutput` has ``scene, i, j``,
``src`` / ``tgt`` (:class:`~pcrcg.registration.feature_registration.FragmentOutput`: ``points (N, 3)``,
``descriptors (N, D)``, ``overlap (N,)``, ``matchability (N,)``, NumPy, each fragment in its own
frame), the data set's ``transform`` (src -> tgt) and ``color_coverage`` (nan without color).

Everything the model needs (sizes, neighbour limits, the projection settings) comes from the
checkpoint. From ``cfg`` only ``trainer.cache_dir`` is read: where the fragments' neighbour pyramids are
kept between runs (none: built in memory), shared with training.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

from pcrcg.models.module import PairOutput
from pcrcg.models.train import infer, load_module


def predict_benchmark(cfg: Any, data_root: str | Path, checkpoint: str | Path, benchmark: str,
                      device: str | None = "cpu", max_pairs: int | None = None,
                      progress: bool = True) -> Iterator[PairOutput]:
    """Outputs of every pair of ``benchmark`` (``3DMatch`` / ``3DLoMatch``) of the data at ``data_root``."""
    module = load_module(checkpoint, device=None if device in (None, "auto") else device)
    trainer = (cfg.get("trainer") if hasattr(cfg, "get") else None) or {}
    yield from infer(module, data_root, benchmark, max_pairs=max_pairs, progress=progress,
                     cache_dir=trainer.get("cache_dir"))
