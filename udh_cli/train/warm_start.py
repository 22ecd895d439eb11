"""Where a run starts from: the architecture ``--init`` implies, a shipped name or checkpoint path resolved, and
weights (whole, or only the encoder) loaded into a new network with clear errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from udh_cli.errors import UdhError
from udh_cli.train.checkpoint import load_checkpoint
from udh_cli.train.config import DEFAULT_ARCH

# (from, to) architectures where --init widens the first regressor layer (new channels start at zero).
WIDENINGS = {("corr", "corr-global")}
# (from, to) architectures where --init takes the encoder only: a matcher starts from a trained network's encoder.
ENCODER_INITS = {("corr", "matcher"), ("corr-global", "matcher")}


def init_arch(init: str | None, mode: str = "unsupervised") -> str:
    """The architecture a run has when none is asked for: ``matcher`` for ``--mode match``; else the
    checkpoint's own when fine-tuning from ``init`` (a checkpoint or shipped name), :data:`DEFAULT_ARCH` without."""
    if mode == "match":
        return "matcher"
    if not init:
        return DEFAULT_ARCH
    return str(load_checkpoint(resolve_init(init))["config"]["arch"])


def resolve_init(init: str) -> Path:
    """A checkpoint path, or the name of a shipped model ("unsupervised", "supervised")."""
    path = Path(init)
    if path.exists() and not path.is_dir():  # a FIFO or device too: load_checkpoint refuses it by name
        return path
    from udh_cli.models_catalog import shipped_checkpoint

    return shipped_checkpoint(init)


def load_weights(model: torch.nn.Module, state: dict[str, Any], source: str) -> None:
    """Load a checkpoint's weights into ``model``; weights that do not fit are a clear error, not a traceback."""
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise UdhError(f"{source}: its weights do not fit the {state['config']['arch']} network ({str(exc).splitlines()[0]})") from None


def load_encoder(model: torch.nn.Module, state: dict[str, Any], source: str) -> None:
    """Load only the ``encoder.*`` weights of a checkpoint (a regressing network's) into ``model`` (a matcher)."""
    encoder = {name: tensor for name, tensor in state["model"].items() if name.startswith("encoder.")}
    try:
        missing = [name for name in model.state_dict() if name.startswith("encoder.") and name not in encoder]
        if missing:
            raise RuntimeError(f"no weight for {missing[0]}")
        model.load_state_dict(encoder, strict=False)
    except RuntimeError as exc:
        raise UdhError(f"{source}: its encoder does not fit the {type(model).__name__} ({str(exc).splitlines()[0]})") from None
