"""Homography estimators behind one interface (see :mod:`udh_cli.estimators.base`)."""

from typing import TYPE_CHECKING

from udh_cli.estimators.registry import DEFAULT_METHOD, ESTIMATORS, create_estimator, estimator_names

if TYPE_CHECKING:  # for type checkers and editors; at run time they load on first use (__getattr__ below)
    from udh_cli.estimators.base import Estimate, Estimator, require_ok

__all__ = ["DEFAULT_METHOD", "ESTIMATORS", "Estimate", "Estimator", "create_estimator", "estimator_names", "require_ok"]

_FROM_BASE = ("Estimate", "Estimator", "require_ok")


def __getattr__(name: str):
    # The interface loads on first use, by name: it needs NumPy, and the command line lists the names without it.
    if name in _FROM_BASE:
        import importlib

        return getattr(importlib.import_module("udh_cli.estimators.base"), name)
    raise AttributeError(f"module 'udh_cli.estimators' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)  # the names loaded on first use too, which the module's namespace does not hold
