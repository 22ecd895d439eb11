"""udh: fast, robust homography estimation and UAV image mosaicking.

Everything the ``udh`` command does is available from here; the CLI is a thin layer over it.
"""

from typing import TYPE_CHECKING

from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators.registry import create_estimator, estimator_names
from udh_cli.version import __version__

if TYPE_CHECKING:  # for type checkers and editors; at run time they load on first use (__getattr__ below)
    from udh_cli.estimators.base import Estimate, Estimator
    from udh_cli.mosaic.arrays import MosaicResult, mosaic_images

__all__ = ["Estimate", "EstimationFailed", "Estimator", "MosaicResult", "UdhError", "create_estimator", "estimator_names", "mosaic_images",
           "__version__"]

# Names loaded on first use, by name -> their module: ``import udh_cli`` (and ``udh --help``) stays free of NumPy, and
# the mosaic package is not imported while this one is.
_LAZY = {"Estimate": "udh_cli.estimators.base", "Estimator": "udh_cli.estimators.base",
         "mosaic_images": "udh_cli.mosaic.arrays", "MosaicResult": "udh_cli.mosaic.arrays"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'udh_cli' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)  # the names loaded on first use too, which the module's namespace does not hold
