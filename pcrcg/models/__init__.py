"""The 3D network stage: KPConv + Predator, losses, the Lightning module and data module.

Public API (imported lazily, so ``import pcrcg.models`` stays cheap):

* :class:`~pcrcg.models.predator.Predator` / :func:`~pcrcg.models.predator.build_predator`
  ``(model_cfg, in_dim)``; :class:`~pcrcg.models.predator.PredatorConfig`.
* :class:`~pcrcg.models.geotransformer.GeoTransformer` / :func:`~pcrcg.models.geotransformer.build_geotransformer`
  ``(model_cfg, in_dim)`` (``model=geotransformer``; its package: :mod:`pcrcg.models.geotransformer`).
* :class:`~pcrcg.models.cofinet.CoFiNet` / :func:`~pcrcg.models.cofinet.build_cofinet` ``(model_cfg, in_dim)``
  (``model=cofinet``; its package: :mod:`pcrcg.models.cofinet`).
* :class:`~pcrcg.models.losses.PredatorLoss`, :func:`~pcrcg.models.losses.circle_loss`,
  :func:`~pcrcg.models.losses.weighted_bce`.
* :class:`~pcrcg.models.module.PCRCGModule`, :class:`~pcrcg.models.module.PairOutput`,
  :class:`~pcrcg.registration.feature_registration.FragmentOutput` (its home is the registration stage,
  whose input it is).
* :class:`~pcrcg.models.datamodule.PairDataModule`, :class:`~pcrcg.models.datamodule.PairCollate`,
  :class:`~pcrcg.models.datamodule.PairBatch`.
* :func:`pcrcg.models.train.train` ``(cfg) -> checkpoint path`` (import it from the submodule:
  ``pcrcg.models.train`` is the module's name), :func:`~pcrcg.models.train.infer`,
  :func:`~pcrcg.models.train.infer_clouds`, :func:`~pcrcg.models.train.load_module`.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable, Mapping

_EXPORTS = {
    "Predator": "predator", "PredatorConfig": "predator", "PredatorOutput": "predator", "build_predator": "predator",
    "GeoTransformer": "geotransformer", "build_geotransformer": "geotransformer",
    "CoFiNet": "cofinet", "build_cofinet": "cofinet",
    "PredatorLoss": "losses", "LossConfig": "losses", "circle_loss": "losses", "weighted_bce": "losses",
    "PCRCGModule": "module", "FragmentOutput": "module", "PairOutput": "module", "OptimConfig": "module",
    "PairDataModule": "datamodule", "PairCollate": "datamodule", "PairBatch": "datamodule",
    "AugmentConfig": "datamodule",
    "infer": "train", "infer_clouds": "train", "load_module": "train",
    "save_pair_output": "train", "load_pair_output": "train",
}


def lazy_exports(package: str, exports: Mapping[str, str]) -> Callable[[str], Any]:
    """A package's module-level ``__getattr__``: ``name`` in ``exports`` is imported from the submodule
    ``<package>.<exports[name]>`` when first asked for (the subpackages of pcrcg.models use it too)."""

    def __getattr__(name: str) -> Any:
        if name in exports:
            return getattr(importlib.import_module(f"{package}.{exports[name]}"), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__


__getattr__ = lazy_exports(__name__, _EXPORTS)


__all__ = sorted(_EXPORTS)
