"""``python -m pcrcg.pretrain2d [profile=tiny|cpu|paper] [data=...] [encoder2d.arch=...] [key=value ...]``

Pri3D-style 2D pretraining (see :mod:`pcrcg.pretrain2d.core`). Progress and messages go to standard
error and the log lines before the last; the last line of standard output is the result as one JSON
object. A bad setting or missing data exits with status 2 and a message naming it.
"""

from __future__ import annotations

import json
import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pcrcg.cli import one_line_errors


@hydra.main(version_base="1.3", config_path="../../conf", config_name="pretrain2d")
def main(cfg: DictConfig) -> None:
    from pcrcg.pretrain2d.core import pretrain

    try:
        base = HydraConfig.get().runtime.cwd
    except ValueError:  # pragma: no cover - called without Hydra
        base = None
    with one_line_errors("pcrcg.pretrain2d"):  # a bad setting or file: one line, exit 2; Ctrl-C: one line
        result = pretrain(cfg, base_dir=base, log=lambda m: print(m, file=sys.stderr, flush=True))
    print(json.dumps(result, default=str), flush=True)


if __name__ == "__main__":
    with one_line_errors("pcrcg.pretrain2d"):
        main()
