"""UAV mosaicking over the Estimator interface: ``run_mosaic(folder_or_video, "mosaic.png", MosaicConfig())``.

One folder per stage, called in order by :func:`.run.run_mosaic` (:mod:`.run`): ``inputs/`` (frames, metadata,
lens), ``pairs/`` (pair estimation, workers, the pair cache), ``solve/`` (chaining, loop closure, the global
solve), ``render/`` (gains, seams, compositing), ``georef/`` (GPS, ground control, GeoTIFFs), ``outputs/``
(every file's name, :class:`.outputs.files.RunFiles`, and writing them together); :mod:`.config` holds the
settings and :mod:`.sidecar` the record of a run. ``live/`` runs them on a folder being written.
"""

from udh_cli.mosaic.live.follow import FollowConfig
from udh_cli.mosaic.live.run import run_live
from udh_cli.mosaic.config import DEFAULT_METHOD, MosaicConfig
from udh_cli.mosaic.run import run_mosaic
from udh_cli.mosaic.report import Reporter

__all__ = ["DEFAULT_METHOD", "FollowConfig", "MosaicConfig", "Reporter", "run_live", "run_mosaic"]
