"""GeoTransformer (geometric transformer + optimal-transport point matching + local-to-global
registration) on the project's KPConv, one module per concept:

* :mod:`.config`: settings (radii in voxels; imports no torch, so the run's config check reads it);
  :mod:`.model`: the network (KPConv-FPN backbone, superpoints, point matching, ``register``);
* :mod:`.embedding`: the geometric structure embedding; :mod:`.transformer`: self / cross attention;
* :mod:`.superpoints`: patches, ground-truth overlaps, superpoint matching, training targets;
* :mod:`.transport`: Sinkhorn with a dustbin; :mod:`.lgr`: point pairs and local-to-global registration;
* :mod:`.loss`: overlap-aware circle loss and point-matching loss.

Names are imported lazily (``from pcrcg.models.geotransformer import build_geotransformer``).
"""

from __future__ import annotations

from pcrcg.models import lazy_exports

_EXPORTS = {
    "GeoLossConfig": "config", "GeoTransformerConfig": "config", "geotransformer_loss": "loss",
    "GeoOutput": "model", "GeoTransformer": "model", "build_geotransformer": "model",
}


__getattr__ = lazy_exports(__name__, _EXPORTS)


__all__ = sorted(_EXPORTS)
