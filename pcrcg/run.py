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

from pcrcg.cli import one_line_errors
from pcrcg.config import CONF_DIR, check_overrides
from pcrcg.errors import PcrcgError
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


def cli_search_dirs(argv: Sequence[str]) -> list[Path]:
    """Config folders named by ``--config-path/-cp`` (replaces conf/) and ``--config-dir/-cd``."""
    dirs = [CONF_DIR]
    for i, arg in enumerate(argv):
        for flag in ("--config-path", "-cp", "--config-dir", "-cd"):
            value = None
            if arg == flag and i + 1 < len(argv):
                value = argv[i + 1]
            elif arg.startswith(flag + "="):
                value = arg.split("=", 1)[1]
            if value is not None:
                p = Path(value).resolve()
                dirs = [p] if flag in ("--config-path", "-cp") else [*dirs, p]
    return dirs


def cli_overrides(argv: Sequence[str]) -> list[str]:
    """The ``key=value`` overrides among Hydra's command-line arguments."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
            continue
        if arg in ("--config-path", "-cp", "--config-dir", "-cd", "--config-name", "-cn", "--experimental-rerun"):
            skip = True
            continue
        if arg.startswith("-") or "=" not in arg:
            continue
        out.append(arg)
    return out


def main(argv: Sequence[str] | None = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    with one_line_errors("pcrcg.run"):
        if not any(a in ("--help", "-h", "--hydra-help", "--info", "-i", "--cfg", "-c") for a in args):
            overrides = cli_overrides(args)
            check_overrides([o for o in overrides if not o.startswith("hydra")], cli_search_dirs(args))
            check_overrides([o for o in overrides if o.startswith("hydra.")], cli_search_dirs(args))
            if not any(a in ("-m", "--multirun") for a in args):
                check_composes(overrides, cli_search_dirs(args), args)
        _hydra_main()


def check_composes(overrides: Sequence[str], dirs: Sequence[Path], args: Sequence[str]) -> None:
    """Compose a single run's config once before Hydra does, so that an override Hydra cannot apply
    (a key that does not exist, a value of the wrong shape) is one line with exit 2 instead of
    Hydra's multi-line report with exit 1. Sweeps are composed job by job by the multirun callback."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    if len(dirs) != 1 or any(a.startswith(("--config-name", "-cn")) for a in args):
        return  # several config folders or another primary config: left to Hydra
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(Path(dirs[0]).resolve()), version_base="1.3"):
            compose(config_name="run", overrides=[o for o in overrides if not o.startswith("hydra.")])
    except (HydraException, OmegaConfBaseException) as e:
        lines = [ln.strip() for ln in str(e).splitlines()
                 if ln.strip() and not ln.strip().startswith(("full_key", "object_type", "provider=", "Config search"))]
        raise PcrcgError(f"cannot compose the config: {'; '.join(lines[:6])}") from None
    finally:
        GlobalHydra.instance().clear()


if __name__ == "__main__":
    main()
