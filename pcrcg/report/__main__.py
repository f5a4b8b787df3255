"""``python -m pcrcg.report [out_dir=reports/] [profile=cpu] [tables=[window_size,views]]``

(A package's ``__main__``: ``pcrcg/report/`` holds the library, so the entry point lives here.)
A bad setting, option or file is one line on standard error with exit status 2 (:mod:`pcrcg.cli`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pcrcg.cli import check_command_line, one_line_errors
from pcrcg.errors import DataError
from pcrcg.report import generate_report


@hydra.main(version_base="1.3", config_path="../../conf", config_name="report")
def main(cfg: DictConfig) -> None:
    from pcrcg.tracking.store import ui_command

    base = HydraConfig.get().runtime.cwd
    command = " ".join(["python -m pcrcg.report", *HydraConfig.get().overrides.task])
    with one_line_errors("pcrcg.report"):  # a bad setting or file: one line, exit 2; Ctrl-C: one line
        check_files(cfg)
        result = generate_report(cfg, base_dir=base, command=command, require_store=True)
    print(f"[report] {len(result.tables)} tables, {len(result.files)} files in {result.out_dir}")
    print(f"[report] start here: {result.index}")
    print(f"[report] runs: {ui_command(result.tracking_uri)}")


def check_files(cfg: DictConfig) -> None:
    """The files the command line names exist: ``paper_csv`` (null: the copy the package ships)."""
    path = cfg.get("paper_csv")
    if path is not None and not Path(str(path)).is_file():
        raise DataError(path, "the paper's numbers file (paper_csv) does not exist")


if __name__ == "__main__":
    with one_line_errors("pcrcg.report"):  # an option or key Hydra cannot apply: one line, exit 2
        check_command_line("report", sys.argv[1:])
        main()
