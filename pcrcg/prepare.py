"""`python -m pcrcg.prepare data=synthmatch|redkitchen|threedmatch profile=tiny|cpu|paper`

Materialises the chosen data set into ``data.root`` (3DMatch layout). Last line of standard
output: a JSON object with the root and the data set's statistics. A bad setting, option or file is one
line on standard error with exit status 2 (:mod:`pcrcg.cli`).
"""

from __future__ import annotations

import json
import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from pcrcg.cli import check_command_line, one_line_errors
from pcrcg.config import source_key
from pcrcg.data.materialise import prepare_dataset, read_manifest
from pcrcg.errors import ConfigError


@hydra.main(version_base="1.3", config_path="../conf", config_name="prepare")
def main(cfg: DictConfig) -> None:
    with one_line_errors("pcrcg.prepare"):  # a bad setting or file: one line, exit 2; Ctrl-C: one line
        check_force(cfg.force)
        data_cfg = OmegaConf.to_container(cfg.data, resolve=True)
        try:
            root = prepare_dataset(data_cfg, seed=cfg.seed, force=bool(cfg.force))
        except ConfigError as e:  # name the key the user set (profile.synth.width, not data.synth.width)
            source = source_key(cfg, e.setting)
            if source == e.setting:
                raise
            raise ConfigError(source, e.value, e.allowed) from None
        man = read_manifest(root) or {}
        print(json.dumps({"root": str(root), "stats": man.get("stats", {})}))


def check_force(value: object) -> None:
    """``force`` is a boolean (``force=abc`` would otherwise regenerate, as any non-empty string is true)."""
    if not isinstance(value, bool):
        raise ConfigError("force", value, "true | false")


if __name__ == "__main__":
    with one_line_errors("pcrcg.prepare"):  # an option or key Hydra cannot apply: one line, exit 2
        check_command_line("prepare", sys.argv[1:])
        main()
