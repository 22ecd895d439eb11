"""Create estimators by name. The names here are the ``--method`` choices of every command."""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

from udh_cli.errors import UdhError
from udh_cli.estimators.base import Estimator

# name -> (module, class, one-line description). Modules are imported on demand, so that choosing
# "sift" never loads onnxruntime.
ESTIMATORS: dict[str, tuple[str, str, str]] = {
    "sift": ("udh_cli.estimators.features", "SiftRansac", "SIFT + ratio test + RANSAC (5 px)"),
    "orb": ("udh_cli.estimators.features", "OrbRansac", "ORB + ratio test + RANSAC (5 px)"),
    "ecc": ("udh_cli.estimators.ecc", "EccEstimator", "ECC, MOTION_HOMOGRAPHY, from the identity"),
    "identity": ("udh_cli.estimators.identity", "IdentityEstimator", "no motion; the baseline"),
    "unsupervised": ("udh_cli.estimators.deep", "UnsupervisedEstimator", "the unsupervised deep network (onnxruntime)"),
    "supervised": ("udh_cli.estimators.deep", "SupervisedEstimator", "supervised HomographyNet (onnxruntime)"),
    "unsupervised+ecc": ("udh_cli.estimators.refined", "RefinedEstimator", "unsupervised network, then coarse-to-fine ECC"),
    "auto": ("udh_cli.estimators.refined", "AutoEstimator", "unsupervised+ecc, verified; SIFT+ECC when it does not verify"),
}


def estimator_names() -> list[str]:
    """The registered method names, in registry order."""
    return list(ESTIMATORS)


def create_estimator(name: str, **options: Any) -> Estimator:
    """Build the estimator registered as ``name`` with keyword ``options`` (its dataclass fields).

    Raises :class:`UdhError` for an unknown name or option.
    """
    if name not in ESTIMATORS:
        raise UdhError(f"unknown method '{name}'; choose one of: {', '.join(ESTIMATORS)}")
    module_name, class_name, _ = ESTIMATORS[name]
    cls = getattr(importlib.import_module(module_name), class_name)
    accepted = [f.name for f in dataclasses.fields(cls) if f.init] if dataclasses.is_dataclass(cls) else []
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise UdhError(f"method '{name}' does not take {', '.join(unknown)}; it takes: {', '.join(accepted) or 'no options'}")
    return cls(**options)
