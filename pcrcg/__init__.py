"""pcrcg: the PCR-CG ablations as an experiment framework (see README.md).

Importing the package registers the project's OmegaConf resolver, used by ``conf/``:

* ``${pcrcg.times:a,b,...}``: the product of numbers, e.g. the registration's distances as
  multiples of the model's voxel (``${pcrcg.times:2.0,${model.voxel_size}}``).
"""

from __future__ import annotations


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


_register_resolvers()
