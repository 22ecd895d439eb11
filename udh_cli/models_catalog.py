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
}


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
