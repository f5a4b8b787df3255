"""GeoTransformer (geometric transformer + optimal-transport point matching + local-to-global
registration) on the project's KPConv, one module per concept:

* :mod:`.config`: settings (radii in voxels); :mod:`.model`: the network (KPConv-FPN backbone,
  superpoints, point matching, ``register``);
* :mod:`.embedding`: the geometric structure embedding; :mod:`.transformer`: self / cross attention;
* :mod:`.superpoints`: patches, ground-truth overlaps, superpoint matching, training targets;
* :mod:`.transport`: Sinkhorn with a dustbin; :mod:`.lgr`: point pairs and local-to-global registration;
* :mod:`.loss`: overlap-aware circle loss and point-matching loss.
"""

from pcrcg.models.geotransformer.config import GeoLossConfig, GeoTransformerConfig
from pcrcg.models.geotransformer.loss import geotransformer_loss
from pcrcg.models.geotransformer.model import GeoOutput, GeoTransformer, build_geotransformer

__all__ = ["GeoLossConfig", "GeoTransformerConfig", "GeoOutput", "GeoTransformer", "build_geotransformer",
           "geotransformer_loss"]
