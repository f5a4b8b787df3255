"""The paper tables' sweeps, read from where they are written once: ``conf/experiment/<table>.yaml``.

``python -m pcrcg.experiments --jobs [EXPERIMENT ...]`` prints one line per job of those experiments'
sweeps (every combination of their ``hydra.sweeper.params`` axes), ``<experiment> key=value ...``, the
form ``sweeps/lib.sh``'s ``job`` takes; with no name, the experiments of ``sweeps/all_tables.sh``'s
order (:data:`TABLE_ORDER`). ``--experiments`` prints the names alone. The sweep scripts read their job
lists from here, so an axis added to an experiment file is swept without editing any script.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path
from typing import Sequence

from omegaconf import OmegaConf

from pcrcg.config import CONF_DIR
from pcrcg.errors import ConfigError

# the order of the tables' sweeps (later tables reuse models trained by earlier ones: main_results trains
# Predator and PCR-CG, which ransac_budget, window_size 11, views_explicit 2, icp_init and explicit_input reuse; the two other
# backbones come last: they train their own models). Every file of conf/experiment/ is listed (tests/test_experiments.py).
TABLE_ORDER = ("main_results", "ransac_budget", "window_size", "views", "views_explicit", "backbone_2d", "projection",
               "icp_init", "sift_dlt", "explicit_input", "geotransformer", "cofinet")


def sweep_axes(experiment: str, conf_dir: Path = CONF_DIR) -> dict[str, list[str]]:
    """``{key: [value, ...]}`` of ``conf/experiment/<experiment>.yaml``'s ``hydra.sweeper.params``, each
    value as Hydra's override grammar reads it (``a,b`` is two values; ``'[1,2]'`` one)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    path = Path(conf_dir) / "experiment" / f"{experiment}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in (Path(conf_dir) / "experiment").glob("*.yaml"))
        raise ConfigError("experiment", experiment, "one of " + ", ".join(known))
    params = OmegaConf.select(OmegaConf.load(path), "hydra.sweeper.params", default=None) or {}
    parser = OverridesParser.create()
    axes: dict[str, list[str]] = {}
    for key, value in params.items():
        override = parser.parse_overrides([f"{key}={value}"])[0]
        axes[str(key)] = (list(override.sweep_string_iterator()) if override.is_sweep_override()
                          else [override.get_value_element_as_str()])
    return axes


def experiment_jobs(experiment: str, conf_dir: Path = CONF_DIR) -> list[list[str]]:
    """One ``[key=value, ...]`` per job of the experiment's sweep (the axes' product, in their order);
    ``[[]]`` for an experiment without axes (one job)."""
    axes = sweep_axes(experiment, conf_dir)
    return [[f"{k}={v}" for k, v in zip(axes, combo)] for combo in itertools.product(*axes.values())]


def main(argv: Sequence[str] | None = None) -> int:
    from pcrcg.cli import one_line_errors

    ap = argparse.ArgumentParser(prog="python -m pcrcg.experiments", description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help=f"experiments (default: {' '.join(TABLE_ORDER)})")
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--jobs", action="store_true", help="one line per job: <experiment> key=value ...")
    what.add_argument("--experiments", action="store_true", help="the experiment names, one per line")
    args = ap.parse_args(argv)
    names = args.names or list(TABLE_ORDER)
    with one_line_errors("pcrcg.experiments"):
        lines = names if args.experiments else [" ".join([n, *job]) for n in names for job in experiment_jobs(n)]
    sys.stdout.write("".join(f"{line}\n" for line in lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
