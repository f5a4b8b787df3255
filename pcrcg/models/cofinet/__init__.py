"""CoFiNet (coarse-to-fine correspondences, Yu et al., NeurIPS 2021) on the project's KPConv, one
module per concept:

* :mod:`.config`: settings (radii in voxels; imports no torch, so the run's config check reads it);
* :mod:`.attention`: attentional propagation (self / cross, masked for padded patches);
* :mod:`.matching`: the coarse ground truth (overlap-aware node matching mask), coarse selection,
  fine ground truth and fine correspondence extraction;
* :mod:`.model`: the network (KPConv encoder, attention, coarse matching layer, decoder, density-adaptive
  fine matching in node patches) and ``correspondences``;
* :mod:`.loss`: the coarse (overlap-aware) and fine matching losses.

Sinkhorn with a dustbin and the point-to-node patches are GeoTransformer's
(:mod:`pcrcg.models.geotransformer.transport`, :mod:`pcrcg.models.geotransformer.superpoints`), imported.
Names are imported lazily (``from pcrcg.models.cofinet import build_cofinet``).
"""

from __future__ import annotations

from pcrcg.models import lazy_exports

_EXPORTS = {
    "CoFiLossConfig": "config", "CoFiNetConfig": "config", "cofinet_loss": "loss",
    "CoFiOutput": "model", "CoFiNet": "model", "build_cofinet": "model",
}


__getattr__ = lazy_exports(__name__, _EXPORTS)


__all__ = sorted(_EXPORTS)
