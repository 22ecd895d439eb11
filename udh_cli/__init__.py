"""udh: fast, robust homography estimation and UAV image mosaicking.

Everything the ``udh`` command does is available from here; the CLI is a thin layer over it.
"""

from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators import Estimate, Estimator, create_estimator, estimator_names

__version__ = "0.1.0"

__all__ = ["Estimate", "EstimationFailed", "Estimator", "UdhError", "create_estimator", "estimator_names", "__version__"]
