"""Checkpoints: atomic writes, safe loads (``weights_only=True``), checked contents."""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import torch

from udh_cli.errors import UdhError
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


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a udh checkpoint without unpickling arbitrary objects, and check that it is one of ours."""
    path = Path(path)
    if not path.is_file():
        raise UdhError(f"{path}: no such checkpoint file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling/format problem means "not a checkpoint"
        raise UdhError(f"{path}: not a readable udh checkpoint ({type(exc).__name__}); give a .pt written by `udh train`") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise UdhError(f"{path}: not a udh checkpoint (no '{CHECKPOINT_FORMAT}' marker)")
    for key in ("model", "config", "step", "normalization"):
        if key not in state:
            raise UdhError(f"{path}: the checkpoint lacks '{key}'; it is incomplete or foreign")
    for name, tensor in state["model"].items():
        if torch.is_floating_point(tensor) and not torch.isfinite(tensor).all():
            raise UdhError(f"{path}: weight '{name}' holds NaN or infinite values")
    mean, std = state["normalization"]["mean"], state["normalization"]["std"]
    if not (math.isfinite(mean) and math.isfinite(std) and std > 0):
        raise UdhError(f"{path}: the stored normalisation (mean {mean}, std {std}) is unusable")
    return state
