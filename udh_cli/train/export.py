"""``udh export-onnx``: the CNN alone to ONNX, with the metadata the estimator needs, checked for parity.

The DLT and rescaling run in the numpy geometry core at inference, so the graph is just the network:
``patches (N, 2, S, S)`` standardised float32 -> ``offsets (N, 4, 2)`` pixels, with a dynamic batch. A
``matcher`` exports its descriptor half instead: ``images (N, 1, H, W)`` -> ``descriptors (N, C, H/4, W/4)``,
with dynamic batch and size (H and W multiples of 4); the matching runs in numpy
(:mod:`udh_cli.estimators.matching`).
"""

from __future__ import annotations

import contextlib
import io
import logging
import warnings
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from udh_cli.errors import UdhError
from udh_cli.files import check_replaceable, write_output
from udh_cli.images import check_output_path
from udh_cli.onnx_model import LICENCE_KEY, MODEL_FORMAT, write_metadata
from udh_cli.train.archs import MATCHERS, create_model
from udh_cli.train.checkpoint import load_checkpoint
from udh_cli.train.config import stored_motion

OPSET = 18  # the torch.export-based exporter's lowest


def portable_path(path: str) -> str:
    """``path`` as it means something on another machine: from its last ``data`` folder on (the shared data's
    layout, ``data/flights/seneca/images``), else its last two parts. A shipped model should not carry the
    absolute paths of the machine it was trained on."""
    parts = Path(path).parts
    if "data" in parts:
        return "/".join(parts[len(parts) - 1 - parts[::-1].index("data"):])
    return "/".join(parts[-2:])


def _portable_history(trained_before: dict[str, Any]) -> dict[str, Any]:
    """``trained_before`` (the run it started from: ``init``, ``init_steps``, ``init_data``) with its paths made
    portable (:func:`portable_path`)."""
    out = dict(trained_before)
    if isinstance(out.get("init"), str) and ("/" in out["init"] or "\\" in out["init"]):
        out["init"] = portable_path(out["init"])
    if isinstance(out.get("init_data"), list):
        out["init_data"] = [portable_path(str(p)) for p in out["init_data"]]
    return out


def model_metadata(state: dict[str, Any], licence: str | None = None) -> dict[str, str]:
    """The ONNX metadata (all strings) describing a checkpoint: what the estimator and the model card read.
    ``licence``: the weights' licence, recorded as given (a checkpoint does not know its images' terms)."""
    config = state["config"]
    motion = stored_motion(config)  # nested, or the flat keys of older checkpoints
    recorded = {LICENCE_KEY: " ".join(licence.split())} if licence and licence.strip() else {}
    return {**recorded,
        "udh_format": MODEL_FORMAT,
        "arch": config["arch"],
        "mode": config["mode"],
        "input_size": str(config["patch_size"]),
        "normalization_mean": repr(float(state["normalization"]["mean"])),
        "normalization_std": repr(float(state["normalization"]["std"])),
        "rho": repr(float(config["rho"])),
        "steps": str(int(state["step"])),
        "training_data": json.dumps([portable_path(str(p)) for p in config["data"]]),
        "data_description": str(state.get("data_description", "")),
        "trained_before": json.dumps(_portable_history(state.get("trained_before", {}))),
        "best_val_mace": repr(float(state.get("best_val", float("nan")))),
        # What motion the network saw, so that a user (and the model card) can tell what it was trained for;
        # models exported before these keys existed were trained on the paper's corner perturbation.
        "motion": "paper" if motion is None else "flight",
        "max_heading": repr(float(motion.max_heading)) if motion else "0.0",
        "max_scale": repr(float(motion.scale_range[1])) if motion else "1.0",
        "max_shift": repr(float(motion.max_shift)) if motion else "0.0",
        "residual": repr(float(motion.residual)) if motion else "0.0",
        "convention": "offsets[i] = b_from_a(corner_i) - corner_i, corners TL,TR,BR,BL at pixel centres of the SxS input",
    }


def export_onnx(checkpoint: str | Path, output: str | Path, check_inputs: np.ndarray | None = None,
                overwrite: bool = False, licence: str | None = None) -> dict[str, Any]:
    """Export ``checkpoint`` to ``output`` (written atomically; an existing file only when udh wrote it, or with
    ``overwrite``) and verify it against torch.

    ``check_inputs`` (N, 2, P, P) in [0, 1] adds real patches to the random ones used for the parity check;
    they are resized to the network's S x S input when P differs (``udh export-onnx --check-images`` draws 128).
    ``licence``: the weights' licence, written into the metadata (:data:`~udh_cli.onnx_model.LICENCE_KEY`).
    Returns ``{"path", "max_abs_diff", "metadata"}``; raises :class:`UdhError` when parity fails (> 1e-3 px).
    """
    import onnx
    import onnxruntime as ort

    if Path(output).suffix.lower() != ".onnx":
        raise UdhError(f"{output}: give the exported model a .onnx name")
    if Path(output).exists() and Path(checkpoint).exists() and Path(output).resolve() == Path(checkpoint).resolve():
        raise UdhError(f"{output}: is the checkpoint being exported; choose another output name")
    check_output_path(output)
    check_replaceable(output, overwrite)
    state = load_checkpoint(checkpoint)  # checks the config's fields, patch_size among them
    size = int(state["config"]["patch_size"])
    _check_weights_fit(checkpoint, state, size)
    model = create_model(state["config"]["arch"], size)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise UdhError(f"{checkpoint}: the weights do not fit the '{state['config']['arch']}' architecture ({str(exc).splitlines()[0]})") from None
    model.eval()
    matcher = state["config"]["arch"] in MATCHERS
    if matcher:
        model = _Describer(model)
        dummy = torch.zeros(2, 1, size, size * 4 // 3 // 4 * 4)
        names, dims = ("images", "descriptors"), {0: torch.export.Dim("batch", min=1, max=64),
                                                  2: 4 * torch.export.Dim("height4", min=8, max=1024),
                                                  3: 4 * torch.export.Dim("width4", min=8, max=1024)}
    else:
        dummy = torch.zeros(2, 2, size, size)
        names, dims = ("patches", "offsets"), {0: torch.export.Dim("batch", min=1, max=4096)}
    # The torch.export-based exporter (the current API; the TorchScript one is deprecated). Its own progress
    # lines and warnings about optional operator libraries (torchvision) are not the user's concern.
    exporter_log = logging.getLogger("torch.onnx")
    level = exporter_log.level
    exporter_log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            program = torch.onnx.export(model, (dummy,), dynamo=True, opset_version=OPSET, input_names=[names[0]],
                                        output_names=[names[1]], dynamic_shapes={names[0]: dims}, verbose=False)
    finally:
        exporter_log.setLevel(level)
    buffer = io.BytesIO(program.model_proto.SerializeToString())
    proto = onnx.load_from_string(buffer.getvalue())
    metadata = model_metadata(state, licence)
    write_metadata(proto, metadata)
    onnx.checker.check_model(proto)
    data = proto.SerializeToString()

    # Parity: random inputs and (if given) real patches, standardised as the estimator will do.
    rng = np.random.default_rng(0)
    mean, std = state["normalization"]["mean"], state["normalization"]["std"]
    session = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    if matcher:  # two image sizes, since the graph's size is dynamic; real images are frames of any size
        checks = [rng.random((2, 1, size, dummy.shape[-1]), dtype=np.float32), rng.random((1, 1, 96, 320), dtype=np.float32)]
        if check_inputs is not None:
            checks.append(np.asarray(check_inputs, np.float32)[:8, :1, : size // 4 * 4, : size // 4 * 4])
    else:
        inputs = rng.random((8, 2, size, size), dtype=np.float32)
        if check_inputs is not None:
            inputs = np.concatenate([inputs, _at_input_size(np.asarray(check_inputs, np.float32), size)])
        checks = [inputs]
    max_diff = 0.0
    for inputs in checks:
        standardised = ((inputs - mean) / std).astype(np.float32)
        with torch.no_grad():
            expected = model(torch.from_numpy(standardised)).numpy()
        got = session.run(None, {names[0]: standardised})[0]
        max_diff = max(max_diff, float(np.abs(got - expected).max()))
    if not max_diff < 1e-3:
        raise UdhError(f"ONNX and torch disagree by {max_diff:.3g} {'in a descriptor' if matcher else 'px'}; the export is not trustworthy")
    write_output(output, data, overwrite)
    return {"path": str(output), "max_abs_diff": max_diff, "metadata": metadata}


class _Describer(torch.nn.Module):
    """A matcher's exported half: images to descriptors (:meth:`DenseMatcher.describe`)."""

    def __init__(self, matcher: torch.nn.Module):
        super().__init__()
        self.matcher = matcher

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.matcher.describe(images)


def _check_weights_fit(checkpoint: str | Path, state: dict[str, Any], size: int) -> None:
    """Refuse weights that do not fit the checkpoint's network at ``size`` before that network is built: a
    damaged patch_size can ask for gigabytes (the network is laid out on torch's 'meta' device, which
    allocates nothing)."""
    arch = state["config"]["arch"]
    with torch.device("meta"):
        skeleton = create_model(arch, size)
    expected = {name: tuple(t.shape) for name, t in skeleton.state_dict().items()}
    found = {name: tuple(t.shape) for name, t in state["model"].items()}
    differing = sorted(name for name in expected.keys() | found.keys() if expected.get(name) != found.get(name))
    if differing:
        name = differing[0]
        example = (f"'{name}' is not one of its weights" if name not in expected else f"'{name}' is missing" if name not in found
                   else f"'{name}' is {found[name]} where {expected[name]} is needed")
        raise UdhError(f"{checkpoint}: the weights do not fit the '{arch}' architecture at {size}px patches ({len(differing)} tensors differ; "
                       f"{example}); the checkpoint is damaged or foreign")


def _at_input_size(patches: np.ndarray, size: int) -> np.ndarray:
    """(N, 2, P, P) check patches -> (N, 2, S, S), resized whole as the estimator resizes its images."""
    if patches.ndim != 4 or patches.shape[1] != 2:
        raise UdhError(f"parity-check patches must be (N, 2, P, P), got {patches.shape}")
    if patches.shape[2:] == (size, size):
        return patches
    return np.stack([[cv2.resize(p, (size, size), interpolation=cv2.INTER_AREA) for p in pair] for pair in patches])
