"""Where the shipped models live: data, not code scattered through loaders.

The files sit in the top-level ``models/`` folder of a checkout, which installs as the package
``udh_cli.models``, so the same lookup works from a checkout, an editable install and a wheel.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from udh_cli.errors import UdhError

# method name -> file stem in models/ (float32 networks; the .pt files beside them are for fine-tuning)
SHIPPED_MODELS = {
    "unsupervised": "udh-unsupervised",
    "unsupervised-refine": "udh-unsupervised-refine",  # the fine stage run after the coarse one
    "unsupervised-flight": "udh-unsupervised-flight",  # a second coarse stage, for whole frames with flight motion
    "unsupervised-matcher": "udh-unsupervised-matcher",  # dense descriptors for the global match of doubted pairs
    "supervised": "udh-supervised",
}
# int8 copies (`udh quantize`) of some of them, for inference only: the default where shipped (DeepEstimator)
SHIPPED_INT8 = {
    "unsupervised": "udh-unsupervised-int8",
    "unsupervised-refine": "udh-unsupervised-refine-int8",
    "unsupervised-flight": "udh-unsupervised-flight-int8",
}
PRECISIONS = ("int8", "fp32")

# The terms of the shipped weights, by the images they were trained on (models/README.md, "Data and licenses"); every
# shipped ONNX file records its set's text in its metadata (onnx_model.LICENCE_KEY), and `udh estimate --help` shows them.
WEIGHTS_LICENCES = {
    "research": "research use only: trained on RSSCN7 and BSDS500, research image collections without a licence for "
                "other use",
    "permissive": "MIT, as udh: trained only on CC0, public-domain, BSD-2-Clause and CC BY images and procedural "
                  "grounds, whose authors models/README.md credits",
}
# catalogue name -> its key in WEIGHTS_LICENCES
SHIPPED_LICENCE = {"unsupervised": "permissive", "unsupervised-refine": "permissive", "unsupervised-flight": "permissive",
                   "unsupervised-matcher": "permissive", "supervised": "research"}


@dataclass(frozen=True)
class ShippedRoles:
    """The names (keys of :data:`SHIPPED_MODELS`) of the shipped networks a learned method runs, by role; a name
    may have no file shipped (:func:`has_shipped` says), e.g. the supervised method has no refinement network.

    Attributes:
        coarse: the first network of the cascade.
        refine: the refinement network run after it, and in the tile stage.
        flight: a second coarse network, trained with real flight motion, whose cascade competes with the first.
        matcher: the dense descriptors of the global match.
    """

    coarse: str
    refine: str
    flight: str
    matcher: str

    @classmethod
    def of(cls, method: str) -> "ShippedRoles":
        """The roles of the learned method ``method``: its own name and ``<method>-<role>``, as the catalogue names them."""
        return cls(method, f"{method}-refine", f"{method}-flight", f"{method}-matcher")


def licence_help() -> str:
    """The terms of each set of shipped weights and the methods that run them, one sentence a set (``udh estimate
    --help``)."""
    methods: dict[str, list[str]] = {}
    for name, key in SHIPPED_LICENCE.items():
        if "-" not in name:  # a method's own network, not one of its roles
            methods.setdefault(key, []).append(name + (" (also inside auto)" if name == "unsupervised" else ""))
    return " ".join(f"The weights of {' and '.join(names)}: {WEIGHTS_LICENCES[key]}." for key, names in methods.items())


def models_dir() -> Path:
    """The folder holding the shipped ``.onnx`` (inference) and ``.pt`` (fine-tuning) files.

    Installed (wheel, ``pip install .`` or editable), it is the package ``udh_cli.models``. Imported straight
    from a checkout (``python -m udh_cli`` or pytest run inside it, whatever is installed), the source
    tree has no such package: the checkout's own top-level ``models/`` folder is used.
    """
    try:
        return Path(str(resources.files("udh_cli.models")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[1] / "models"


def _shipped_path(name: str, suffix: str) -> Path:
    return models_dir() / f"{SHIPPED_MODELS[name]}{suffix}"


def _shipped(name: str, suffix: str) -> Path:
    if name not in SHIPPED_MODELS:
        raise UdhError(f"no shipped model called '{name}'; choose one of: {', '.join(SHIPPED_MODELS)}, or give a file path")
    path = _shipped_path(name, suffix)
    if not path.is_file():
        raise UdhError(f"the shipped {name} model is missing ({path}); reinstall udh or pass --model PATH")
    return path


def check_precision(precision: str | None) -> None:
    """Raise :class:`UdhError` unless ``precision`` is "int8", "fp32" or ``None``."""
    if precision not in (None, *PRECISIONS):
        raise UdhError(f"unknown precision '{precision}'; choose {' or '.join(PRECISIONS)}")


def _int8_path(name: str) -> Path | None:
    return models_dir() / f"{SHIPPED_INT8[name]}.onnx" if name in SHIPPED_INT8 else None


def has_shipped(name: str, precision: str | None = "fp32") -> bool:
    """Whether the shipped ONNX network ``name`` is installed at ``precision`` (``None``: at either)."""
    int8 = _int8_path(name)
    has_int8 = int8 is not None and int8.is_file()
    has_fp32 = name in SHIPPED_MODELS and _shipped_path(name, ".onnx").is_file()
    return {"int8": has_int8, "fp32": has_fp32, None: has_int8 or has_fp32}[precision]


def has_refinement_stage(name: str, model: str | None, refine_model: str | None) -> bool:
    """Whether the learned method ``name`` gets a refinement stage: a ``refine_model`` file is given, or no
    ``model`` file is and a shipped refinement network of ``name`` exists (at either precision)."""
    return refine_model is not None or (model is None and has_shipped(ShippedRoles.of(name).refine, precision=None))


def shipped_onnx(name: str, precision: str | None = "fp32") -> Path:
    """The ONNX file of the shipped network ``name`` ("unsupervised", "unsupervised-refine", "supervised") at
    ``precision``: "fp32", "int8" (an error when no int8 copy is shipped) or ``None`` (int8 where shipped)."""
    check_precision(precision)
    int8 = _int8_path(name)
    if precision != "fp32" and int8 is not None and int8.is_file():
        return int8
    if precision == "int8":
        if name not in SHIPPED_MODELS:
            _shipped(name, ".onnx")  # the unknown-name error
        raise UdhError(f"no int8 copy of the {name} model is shipped; use precision fp32, or make one with `udh quantize`")
    return _shipped(name, ".onnx")


# Shipped networks whose weights for fine-tuning are kept with their training run (weights.pt: the weights the ONNX
# file was exported from, without the optimiser state; checkpoint.pt: the resumable run) rather than as a .pt beside it.
SHIPPED_RUNS = {"unsupervised-refine": "training/permissive-refine/weights.pt",
                "unsupervised-flight": "training/permissive-flight/weights.pt",
                "unsupervised-matcher": "training/permissive-matcher/checkpoint.pt"}


def shipped_checkpoint(name: str) -> Path:
    """The torch checkpoint of a shipped model, for ``udh train --init``."""
    if name in SHIPPED_RUNS and not _shipped_path(name, ".pt").is_file():
        path = models_dir() / SHIPPED_RUNS[name]
        if not path.is_file():
            raise UdhError(f"the shipped {name} model's weights are missing ({path}); reinstall udh or pass --init PATH")
        return path
    return _shipped(name, ".pt")
