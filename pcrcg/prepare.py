"""`python -m pcrcg.prepare data=synthmatch|redkitchen|threedmatch profile=tiny|cpu|paper`

Materialises the chosen data set into ``data.root`` (3DMatch layout). Last line of standard
output: a JSON object with the root and the data set's statistics.
"""

from __future__ import annotations

import json

import hydra
from omegaconf import DictConfig, OmegaConf

from pcrcg.cli import one_line_errors
from pcrcg.config import source_key
from pcrcg.data.materialise import prepare_dataset, read_manifest
from pcrcg.errors import ConfigError


@hydra.main(version_base="1.3", config_path="../conf", config_name="prepare")
def main(cfg: DictConfig) -> None:
    with one_line_errors("pcrcg.prepare"):  # a bad setting or file: one line, exit 2; Ctrl-C: one line
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


if __name__ == "__main__":
    with one_line_errors("pcrcg.prepare"):
        main()
