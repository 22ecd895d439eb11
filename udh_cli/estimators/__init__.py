"""Homography estimators behind one interface (see :mod:`udh_cli.estimators.base`)."""

from udh_cli.estimators.base import Estimate, Estimator, require_ok
from udh_cli.estimators.registry import DEFAULT_METHOD, ESTIMATORS, create_estimator, estimator_names

__all__ = ["DEFAULT_METHOD", "ESTIMATORS", "Estimate", "Estimator", "create_estimator", "estimator_names", "require_ok"]
