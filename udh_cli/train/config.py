"""What defines a training run: :class:`TrainConfig` and its defaults, without torch, so that the command line
takes its defaults from here."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from udh_cli.errors import UdhError
from udh_cli.generator_settings import MotionConfig

DEFAULT_ARCH = "corr"  # the CPU-friendly network of udh_cli.train.archs
PAPER_LR = {"unsupervised": 1e-4, "supervised": 5e-4}  # the paper's Adam learning rates
# Default rates by --mode: the paper's, and for the matcher (a fine-tune of a trained encoder plus a new block).
DEFAULT_LR = {**PAPER_LR, "match": 3e-4}
MOTIONS = ("paper", "flight")  # --motion: the paper's corner perturbation (TrainConfig.motion None), or flight motion
# The flat keys a run's stored settings (config.json, checkpoints) held before TrainConfig nested its flight motion,
# with the MotionConfig field each became; max_scale became scale_range (1 / it, it).
FLAT_MOTION_KEYS = ("max_heading", "max_scale", "max_shift", "min_overlap", "residual")
PHOTOMETRIC_SPACES = ("intensity", "contrast")  # what the unsupervised loss compares (train.losses)
DEFAULT_STEPS = 20000
DEFAULT_REAL_FRACTION = 0.5  # share of a mixed batch from real flight pairs


@dataclass
class TrainConfig:
    """Everything that defines a run; stored in every checkpoint and in ``config.json``.

    Attributes:
        mode: "unsupervised" (photometric L1, no labels), "supervised" (L2 on the 4-point labels) or "match"
            (the ``matcher`` descriptors, trained to find each cell's counterpart under synthetic flight motion;
            views are ``patch_size`` high and 4:3).
        data: folders of images (synthetic pairs) or of flights (consecutive real frames), or both.
        data_kind: "auto" (flight folders are recognised by their manifest; pools and flights together
            are mixed), "pool" or "flight".
        real_fraction: with pools and flights together, the share of each batch drawn from the flights.
        source_side: pool images are resized to 320x240 (0, the paper's), or to this longer side with
            pairs drawn from 320x240 windows of them (the scale of the tile stage's tiles).
        arch: architecture name (see :data:`udh_cli.train.archs.ARCHS`).
        patch_size: network input side, pixels.
        rho: largest corner perturbation of synthetic pairs, pixels.
        small_motion_fraction: share of synthetic pairs with a smaller, random rho.
        illumination: random brightness/contrast/gamma on the inputs; occluders: the share of pairs
            (0 to 1) with textured blobs pasted on the inputs. Both are input augmentations: the losses
            see the clean images.
        photometric: what the unsupervised L1 compares: "intensity" (grey values, the paper's) or
            "contrast" (local contrast, blind to vignetting, hot spots and exposure).
        motion: None for the paper's corner perturbation by ``rho``, or the flight motion of whole frames
            (:class:`~udh_cli.generator_settings.MotionConfig`, :mod:`udh_cli.flight_motion`: turn, scale, shift,
            perspective jitter, overlap, and ``residual`` above 0 for a later round of the cascade);
            :func:`flight_motion` makes it from the command line's flags.
        steps: total optimiser steps (None: :data:`DEFAULT_STEPS`, or on resume the run's own total);
            batch: pairs per step and per process.
        lr: Adam learning rate (None: the paper's, 1e-4 unsupervised, 5e-4 supervised).
        betas, eps: Adam's, as in the paper.
        lr_final_fraction: the learning rate decays along a cosine to this fraction of ``lr``.
        seed: seeds data generation and initialisation.
        eval_every, checkpoint_every: in steps. val_pairs: size of the fixed validation set.
        init: a checkpoint (or a shipped model name) to fine-tune from.
        teacher: a checkpoint (or shipped model name) to distil from, unsupervised mode only: the loss adds
            ``teacher_weight`` times the mean absolute difference, in pixels, between this network's offsets and
            the teacher's on the same inputs. No labels are used; the teacher's own answers are the target.
        out: run folder (checkpoint.pt, best.pt, metrics.jsonl, config.json).
    """

    mode: str = "unsupervised"
    data: list[str] = field(default_factory=list)
    data_kind: str = "auto"
    real_fraction: float = DEFAULT_REAL_FRACTION
    source_side: int = 0
    arch: str = DEFAULT_ARCH
    patch_size: int = 128
    rho: float = 32.0
    small_motion_fraction: float = 0.3
    illumination: bool = True
    occluders: float = 0.0
    photometric: str = "intensity"
    motion: MotionConfig | None = None
    steps: int | None = None
    batch: int = 32
    lr: float | None = None
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8
    lr_final_fraction: float = 0.05
    seed: int = 0
    eval_every: int = 250
    checkpoint_every: int = 250
    val_pairs: int = 256
    init: str | None = None
    teacher: str | None = None
    teacher_weight: float = 0.01
    out: str = "runs/udh"

    def learning_rate(self) -> float:
        return DEFAULT_LR[self.mode] if self.lr is None else self.lr

    @classmethod
    def from_dict(cls, stored: dict[str, Any]) -> "TrainConfig":
        """The config a run stored (``asdict`` of one, read back from JSON or a checkpoint), nested or flat: the
        flat keys of earlier runs (``motion`` "paper"/"flight", :data:`FLAT_MOTION_KEYS`, ``rho`` the
        perspective jitter) load to the same values. Raises KeyError, TypeError or ValueError for a damaged one."""
        values = {key: value for key, value in stored.items() if key not in FLAT_MOTION_KEYS}
        values["motion"] = stored_motion(stored)
        if "betas" in values:
            values["betas"] = tuple(values["betas"])
        return cls(**values)


def stored_motion(stored: dict[str, Any]) -> MotionConfig | None:
    """The motion of a run's stored settings (see :meth:`TrainConfig.from_dict`), nested or flat."""
    motion = stored.get("motion")
    if isinstance(motion, dict):
        return MotionConfig(**{**motion, "scale_range": tuple(motion["scale_range"])})
    if motion is None or motion == "paper":
        return None
    if motion != "flight":
        raise ValueError(f"motion {motion!r} is not one of {', '.join(MOTIONS)}")
    flat = {key: float(stored[key]) for key in FLAT_MOTION_KEYS if key in stored}
    return flight_motion("flight", float(stored.get("rho", TrainConfig.rho)), **flat)


def flight_motion(motion: str, perspective: float, max_heading: float = MotionConfig.max_heading,
                  max_scale: float = MotionConfig.scale_range[1], max_shift: float = MotionConfig.max_shift,
                  min_overlap: float = MotionConfig.min_overlap, residual: float = MotionConfig.residual) -> MotionConfig | None:
    """``TrainConfig.motion`` from the command line's flags: None for ``motion`` "paper", else the flight motion
    with these ranges (``max_scale``: the largest scale change, a factor either way; ``perspective``: ``--rho``).

    Raises :class:`UdhError` for an unknown ``motion``, or a ``residual`` without flight motion."""
    if motion not in MOTIONS:
        raise UdhError(f"--motion {motion}: choose one of {', '.join(MOTIONS)}")
    if motion == "paper":
        if residual:
            raise UdhError("--residual trains a later round on flight motion; it needs --motion flight")
        return None
    return MotionConfig(max_heading=max_heading, scale_range=(1.0 / max_scale, max_scale), max_shift=max_shift,
                        perspective=perspective, min_overlap=min_overlap, residual=residual)
