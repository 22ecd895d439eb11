"""udh: fast, robust homography estimation and UAV image mosaicking.

Everything the ``udh`` command does is available from here; the CLI is a thin layer over it.
"""

from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators import Estimate, Estimator, create_estimator, estimator_names

__version__ = "0.1.0"

__all__ = ["Estimate", "EstimationFailed", "Estimator", "MosaicResult", "UdhError", "create_estimator", "estimator_names", "mosaic_images",
           "__version__"]


def __getattr__(name: str):
    # The mosaic API loads on first use, by name: ``import udh_cli`` for estimation stays light, and the mosaic
    # package (which reads ``__version__`` from here) is not imported while this one is.
    if name in ("mosaic_images", "MosaicResult"):
        import importlib

        return getattr(importlib.import_module("udh_cli.mosaic.arrays"), name)
    raise AttributeError(f"module 'udh_cli' has no attribute {name!r}")
