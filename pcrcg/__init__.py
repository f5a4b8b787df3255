"""pcrcg: the PCR-CG ablations as an experiment framework (see README.md).

Importing the package registers the project's OmegaConf resolver, used by ``conf/``:

* ``${pcrcg.times:a,b,...}``: the product of numbers, e.g. the registration's distances as
  multiples of the model's voxel (``${pcrcg.times:2.0,${model.voxel_size}}``).
* ``${pcrcg.pid:}``: this process's id, in the output folders' names after their start time
  (``outputs/run/<experiment>/<time>_<pid>``): two commands started in the same second, e.g. the first jobs of
  a sweep's two lanes, get folders of their own instead of writing (and logging) each other's files.
"""

from __future__ import annotations

import os


def _register_resolvers() -> None:
    try:
        from omegaconf import OmegaConf
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        return

    def times(*values):
        out = 1.0
        for v in values:
            out *= float(v)
        return out

    if not OmegaConf.has_resolver("pcrcg.times"):
        OmegaConf.register_new_resolver("pcrcg.times", times)
    if not OmegaConf.has_resolver("pcrcg.pid"):
        OmegaConf.register_new_resolver("pcrcg.pid", lambda: str(os.getpid()))


_register_resolvers()
