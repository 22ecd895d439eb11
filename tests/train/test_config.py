"""TrainConfig: flight motion nested as a MotionConfig, and every stored run of before still loading."""

from __future__ import annotations

import json
from dataclasses import asdict, fields
from pathlib import Path

import pytest

from udh_cli.errors import UdhError
from udh_cli.generator_settings import MotionConfig
from udh_cli.train.config import FLAT_MOTION_KEYS, TrainConfig, flight_motion

REPO = Path(__file__).resolve().parents[2]
# The committed run folders, and a live run that must still --resume where it is present.
STORED = sorted((REPO / "models" / "training").glob("*/config.json")) + [Path("/work/runs/matcher-any/config.json")]


def as_before(stored: dict) -> MotionConfig | None:
    """The motion a flat config trained on, as the code before nesting built it (its perspective was ``rho``); a
    config written since then (``motion`` nested, or null for the paper's motion) as it is."""
    motion = stored.get("motion", "paper")
    if motion in (None, "paper"):
        return None
    if isinstance(motion, dict):
        return MotionConfig(**{key: tuple(value) if isinstance(value, list) else value for key, value in motion.items()})
    scale, defaults = stored["max_scale"], MotionConfig()
    return MotionConfig(max_heading=stored["max_heading"], scale_range=(1.0 / scale, scale), max_shift=stored["max_shift"],
                        perspective=stored["rho"], min_overlap=stored.get("min_overlap", defaults.min_overlap),
                        residual=stored.get("residual", defaults.residual))


@pytest.mark.parametrize("path", STORED, ids=lambda p: p.parent.name)
def test_an_old_flat_config_loads_to_the_same_values(path):
    if not path.is_file():
        pytest.skip(f"{path} is not here")
    stored = json.loads(path.read_text())
    loaded = TrainConfig.from_dict(stored)
    assert loaded.motion == as_before(stored)
    for key, value in stored.items():
        if key not in FLAT_MOTION_KEYS and key != "motion":
            assert getattr(loaded, key) == (tuple(value) if key == "betas" else value), key
    again = TrainConfig.from_dict(json.loads(json.dumps(asdict(loaded))))  # what a run stores now, read back
    assert again == loaded


def test_flight_motion_is_one_nested_record():
    assert "motion" in {f.name for f in fields(TrainConfig)} and not set(FLAT_MOTION_KEYS) & {f.name for f in fields(TrainConfig)}
    motion = flight_motion("flight", 12.0, max_heading=45.0, max_scale=1.5, residual=8.0)
    assert (motion.max_heading, motion.scale_range, motion.perspective, motion.residual) == (45.0, (1 / 1.5, 1.5), 12.0, 8.0)
    assert flight_motion("paper", 32.0) is None
    stored = asdict(TrainConfig(motion=motion))
    assert stored["motion"]["max_heading"] == 45.0 and TrainConfig.from_dict(stored).motion == motion
    with pytest.raises(UdhError, match="--residual trains a later round on flight motion"):
        flight_motion("paper", 32.0, residual=8.0)
    with pytest.raises(UdhError, match="--motion sideways: choose one of paper, flight"):
        flight_motion("sideways", 32.0)
    with pytest.raises(ValueError, match="'sideways' is not one of paper, flight"):
        TrainConfig.from_dict({"motion": "sideways"})
