"""Homography estimators behind one interface (see :mod:`udh_cli.estimators.base`)."""

from udh_cli.estimators.base import Estimate, Estimator, require_ok
from udh_cli.estimators.registry import ESTIMATORS, create_estimator, estimator_names

__all__ = ["ESTIMATORS", "Estimate", "Estimator", "create_estimator", "estimator_names", "require_ok"]
