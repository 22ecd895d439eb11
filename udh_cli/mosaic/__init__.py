"""UAV mosaicking over the Estimator interface: ``run_mosaic(folder_or_video, "mosaic.png", MosaicConfig())``.

Stages, one module each: :mod:`.frames` (input; :mod:`.lens` undistorts it), :mod:`.pairwise` (batched
estimation, the method then the fallback), :mod:`.graph` (parts, chaining, overlap candidates), :mod:`.solve`
(global least squares), :mod:`.small` (each part drawn small) for :mod:`.gains` (exposure) and :mod:`.seams`,
:mod:`.composite` (canvas and blending), :mod:`.truth` (simulator ground truth);
:mod:`.pipeline` wires them; :mod:`.live` runs them on a folder being written (:mod:`.follow` watches it,
:mod:`.quicklook` draws each frame as it lands).
"""

from udh_cli.mosaic.live.follow import FollowConfig
from udh_cli.mosaic.live.run import run_live
from udh_cli.mosaic.pipeline import DEFAULT_METHOD, MosaicConfig, run_mosaic
from udh_cli.mosaic.report import Reporter

__all__ = ["DEFAULT_METHOD", "FollowConfig", "MosaicConfig", "Reporter", "run_live", "run_mosaic"]
