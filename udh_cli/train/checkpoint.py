"""Checkpoints: atomic writes, safe loads (``weights_only=True``), checked contents."""

from __future__ import annotations

import io
import math
import warnings
from pathlib import Path
from typing import Any

import torch

from udh_cli.errors import UdhError
from udh_cli.files import read_side_file
from udh_cli.images import atomic_write_bytes

CHECKPOINT_FORMAT = "udh-checkpoint-1"


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Write ``state`` (tensors, numbers, strings, lists and dicts only) to ``path`` atomically.

    Weights that are NaN or infinite are refused before anything is written, so a diverged run never
    replaces its last good checkpoint.
    """
    for name, tensor in state.get("model", {}).items():
        if torch.is_floating_point(tensor) and not torch.isfinite(tensor).all():
            raise UdhError(f"weight '{name}' became NaN or infinite; {path} is kept as it was: continue with --resume and a lower --lr")
    buffer = io.BytesIO()
    torch.save({"format": CHECKPOINT_FORMAT, **state}, buffer)
    atomic_write_bytes(path, buffer.getvalue())


MAX_CHECKPOINT_BYTES = 4 * 2**30  # the paper's 34 M-parameter network with Adam's state takes about 0.4 GB


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a udh checkpoint without unpickling arbitrary objects, and check that it is one of ours."""
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        raise UdhError(f"{path}: no such checkpoint file")
    data = read_side_file(path, "", MAX_CHECKPOINT_BYTES)  # a regular file, bounded: never a FIFO that blocks
    try:
        with warnings.catch_warnings():
            # torch's note on a pickle protocol it did not write would come before udh's own line about the file
            warnings.filterwarnings("ignore", message="Detected pickle protocol", category=UserWarning)
            state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling/format problem means "not a checkpoint"
        raise UdhError(f"{path}: not a readable udh checkpoint ({type(exc).__name__}); give a .pt written by `udh train`") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise UdhError(f"{path}: not a udh checkpoint (no '{CHECKPOINT_FORMAT}' marker)")
    for key in ("model", "config", "step", "normalization"):
        if key not in state:
            raise UdhError(f"{path}: the checkpoint lacks '{key}'; it is incomplete or foreign")
    if not isinstance(state["model"], dict) or not all(isinstance(t, torch.Tensor) for t in state["model"].values()):
        raise UdhError(f"{path}: the checkpoint's 'model' is not a set of weights; it is damaged or foreign")
    for name, tensor in state["model"].items():
        if torch.is_floating_point(tensor) and not torch.isfinite(tensor).all():
            raise UdhError(f"{path}: weight '{name}' holds NaN or infinite values")
    normalization = state["normalization"]
    mean, std = (normalization.get("mean"), normalization.get("std")) if isinstance(normalization, dict) else (None, None)
    if not (_is_number(mean) and _is_number(std) and math.isfinite(mean) and math.isfinite(std) and std > 0):
        raise UdhError(f"{path}: the stored normalisation (mean {_short(mean)}, std {_short(std)}) is unusable")
    if not _is_integer(state["step"]) or state["step"] < 0:
        raise UdhError(f"{path}: the stored step count {_short(state['step'])} is not a whole number; the checkpoint is damaged")
    _check_config(path, state["config"])
    return state


MAX_PATCH_SIZE = 512  # px; the shipped networks take 128. Larger inputs would build networks of gigabytes.
# What the loaders rely on in a checkpoint's config: key -> (test, what it must be). Keys marked optional may be absent
# (checkpoints written before they existed).
_CONFIG_FIELDS = {
    "arch": (lambda v: isinstance(v, str), "an architecture name", False),
    "mode": (lambda v: isinstance(v, str), "a training mode", False),
    "patch_size": (lambda v: _is_integer(v) and v % 32 == 0 and 32 <= v <= MAX_PATCH_SIZE, f"a multiple of 32 from 32 to {MAX_PATCH_SIZE}", False),
    "rho": (lambda v: _is_number(v) and math.isfinite(v) and v > 0, "a positive number", False),
    "data": (lambda v: isinstance(v, (list, tuple)) and all(isinstance(d, str) for d in v), "a list of folders", False),
    "motion": (lambda v: v is None or isinstance(v, str) or _is_motion(v), "none, a motion name or flight motion's ranges", True),
    # The flat flight-motion keys of checkpoints written before TrainConfig nested them in "motion".
    "max_heading": (lambda v: _is_number(v) and math.isfinite(v), "a number", True),
    "max_scale": (lambda v: _is_number(v) and math.isfinite(v), "a number", True),
    "max_shift": (lambda v: _is_number(v) and math.isfinite(v), "a number", True),
    "residual": (lambda v: _is_number(v) and math.isfinite(v) and v >= 0, "a number of at least 0", True),
}


def _check_config(path: Path, config: Any) -> None:
    """The config fields export and --init/--teacher/--resume read must be there and of the right kind."""
    if not isinstance(config, dict):
        raise UdhError(f"{path}: the checkpoint's config is not a dict; it is damaged or foreign")
    for key, (test, wanted, optional) in _CONFIG_FIELDS.items():
        if key not in config:
            if optional:
                continue
            raise UdhError(f"{path}: the checkpoint's config lacks '{key}'; it is damaged or foreign")
        if not test(config[key]):
            raise UdhError(f"{path}: the checkpoint's config gives {key} {_short(config[key])}, not {wanted}; it is damaged or foreign")


def _is_motion(value: Any) -> bool:
    """Whether ``value`` is a stored MotionConfig: finite numbers, a (low, high) scale range, a residual of at least 0."""
    if not isinstance(value, dict) or not isinstance(value.get("scale_range"), (list, tuple)) or len(value["scale_range"]) != 2:
        return False
    numbers = [v for key, v in value.items() if key != "scale_range"] + list(value["scale_range"])
    return all(_is_number(v) and math.isfinite(v) for v in numbers) and value.get("residual", 0) >= 0


def _short(value: Any) -> str:
    text = " ".join(repr(value).split())
    return text if len(text) <= 60 else text[:57] + "..."


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)
