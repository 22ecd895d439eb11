"""Where the shipped models live: data, not code scattered through loaders.

The files sit in the top-level ``models/`` folder of a checkout, which installs as the package
``udh_cli.models``, so the same lookup works from a checkout, an editable install and a wheel.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from udh_cli.errors import UdhError

# method name -> file stem in models/
SHIPPED_MODELS = {
    "unsupervised": "udh-unsupervised",
    "unsupervised-refine": "udh-unsupervised-refine",  # the fine stage run after the coarse one
    "supervised": "udh-supervised",
    # int8 copies (`udh quantize`) of the float32 networks above: the default where shipped (see DeepEstimator)
    "unsupervised-int8": "udh-unsupervised-int8",
    "unsupervised-refine-int8": "udh-unsupervised-refine-int8",
}
PRECISIONS = ("int8", "fp32")


def shipped_variant(name: str, precision: str | None) -> str:
    """The shipped model to load for ``name`` at ``precision``: "int8" (its int8 copy, an error when none is
    shipped), "fp32" (the float32 network) or ``None`` (int8 where shipped, else float32)."""
    if precision not in (None, *PRECISIONS):
        raise UdhError(f"unknown precision '{precision}'; choose {' or '.join(PRECISIONS)}")
    if precision == "fp32":
        return name
    if has_shipped(f"{name}-int8"):
        return f"{name}-int8"
    if precision == "int8":
        raise UdhError(f"no int8 copy of the {name} model is shipped; use precision fp32, or make one with `udh quantize`")
    return name


def models_dir() -> Path:
    """The folder holding the shipped ``.onnx`` (inference) and ``.pt`` (fine-tuning) files."""
    return Path(str(resources.files("udh_cli.models")))


def _shipped_path(name: str, suffix: str) -> Path:
    return models_dir() / f"{SHIPPED_MODELS[name]}{suffix}"


def _shipped(name: str, suffix: str) -> Path:
    if name not in SHIPPED_MODELS:
        raise UdhError(f"no shipped model called '{name}'; choose one of: {', '.join(SHIPPED_MODELS)}, or give a file path")
    path = _shipped_path(name, suffix)
    if not path.is_file():
        raise UdhError(f"the shipped {name} model is missing ({path}); reinstall udh or pass --model PATH")
    return path


def has_shipped(name: str) -> bool:
    """Whether the shipped ONNX model ``name`` is installed."""
    return name in SHIPPED_MODELS and _shipped_path(name, ".onnx").is_file()


def shipped_onnx(name: str) -> Path:
    """The ONNX file of a shipped model ("unsupervised" or "supervised")."""
    return _shipped(name, ".onnx")


def shipped_checkpoint(name: str) -> Path:
    """The torch checkpoint of a shipped model, for ``udh train --init``."""
    return _shipped(name, ".pt")
