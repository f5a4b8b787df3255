"""``python -m pcrcg.run [+experiment=<table>] [overrides] [-m]``: run (or sweep) the pipeline.

The work is in :mod:`pcrcg.pipeline`; this module only bridges Hydra and checks the
command-line overrides before Hydra composes them (a bad group option or value fails
here, naming the setting and what is allowed).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from pcrcg.cli import check_command_line, command_line_config_dirs, command_line_overrides, one_line_errors
from pcrcg.config import CONF_DIR, check_overrides
from pcrcg.pipeline import JobInfo, run_job


def search_dirs_from_hydra() -> tuple[Path, ...]:
    """The file-based config folders of the running Hydra app."""
    out = []
    for src in HydraConfig.get().runtime.config_sources:
        if src.schema == "file":
            out.append(Path(src.path))
    return tuple(out) or (CONF_DIR,)


def job_info_from_hydra() -> JobInfo:
    hc = HydraConfig.get()
    multirun = hc.mode == RunMode.MULTIRUN
    return JobInfo(
        output_dir=Path(hc.runtime.output_dir),
        base_dir=Path(hc.runtime.cwd),
        overrides=list(hc.overrides.task),
        choices={k: v for k, v in hc.runtime.choices.items() if v is not None},
        multirun=multirun,
        sweep_dir=str(hc.sweep.dir) if multirun else None,
        search_dirs=search_dirs_from_hydra(),
    )


@hydra.main(version_base="1.3", config_path="../conf", config_name="run")
def _hydra_main(cfg: DictConfig) -> str:
    # a bad value or file: one line, exit 2; Ctrl-C / SIGTERM: one line, exit 130 / 143 (the run is
    # closed as KILLED first). SystemExit passes through Hydra's job runner, which would print a
    # traceback for an exception.
    with one_line_errors("pcrcg.run"):
        return run_job(cfg, job_info_from_hydra()).status


def main(argv: Sequence[str] | None = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    with one_line_errors("pcrcg.run"):
        if not any(a in ("--help", "-h", "--hydra-help", "--info", "-i", "--cfg", "-c") for a in args):
            overrides, dirs = command_line_overrides(args), command_line_config_dirs(args)
            check_overrides([o for o in overrides if not o.startswith("hydra")], dirs)
            check_overrides([o for o in overrides if o.startswith("hydra.")], dirs)
            check_command_line("run", args)  # a single run composed once; sweeps job by job (multirun callback)
        _hydra_main()


if __name__ == "__main__":
    main()
