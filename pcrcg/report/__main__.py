"""``python -m pcrcg.report [out_dir=reports/] [profile=cpu] [tables=[window_size,views]]``

(A package's ``__main__``: ``pcrcg/report/`` holds the library, so the entry point lives here.)
"""

from __future__ import annotations

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pcrcg.cli import one_line_errors
from pcrcg.report import generate_report


@hydra.main(version_base="1.3", config_path="../../conf", config_name="report")
def main(cfg: DictConfig) -> None:
    from pcrcg.tracking.store import ui_command

    base = HydraConfig.get().runtime.cwd
    command = " ".join(["python -m pcrcg.report", *HydraConfig.get().overrides.task])
    with one_line_errors("pcrcg.report"):  # a bad setting: one line, exit 2; Ctrl-C: one line
        result = generate_report(cfg, base_dir=base, command=command)
    print(f"[report] {len(result.tables)} tables, {len(result.files)} files in {result.out_dir}")
    print(f"[report] start here: {result.index}")
    print(f"[report] runs: {ui_command(result.tracking_uri)}")


if __name__ == "__main__":
    with one_line_errors("pcrcg.report"):
        main()
