"""Learning curves from ``metrics.jsonl`` files, drawn with OpenCV (no torch, no plotting library)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from udh_cli.bench.plots import PALETTE, Axes, _legend, _log_limits
from udh_cli.errors import UdhError


def read_metrics(path: str | Path) -> list[dict]:
    """The records of one run's ``metrics.jsonl``; raises :class:`UdhError` if the file is unreadable."""
    try:
        return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    except (OSError, json.JSONDecodeError) as exc:
        raise UdhError(f"{path}: not a readable metrics log ({exc})") from None


def learning_curve_plot(runs: dict[str, list[dict]], key: str = "val_mace_median", size: tuple[int, int] = (640, 400),
                        title: str = "learning curves") -> np.ndarray:
    """Validation corner error against training step, one line per run (log y). (H, W, 3) uint8 BGR."""
    width, height = size
    canvas = np.full((height, width, 3), 255, np.uint8)
    curves = {name: [(r["step"], r[key]) for r in records if key in r] for name, records in runs.items()}
    curves = {name: np.array(points, np.float64) for name, points in curves.items() if points}
    if not curves:
        raise UdhError(f"no '{key}' values in the given logs")
    steps = np.concatenate([c[:, 0] for c in curves.values()])
    values = np.concatenate([c[:, 1] for c in curves.values()])
    axes = Axes(canvas, (80, 40, width - 110, height - 110), (0.0, float(steps.max()) or 1.0), _log_limits(values, 0.1, 1000), ylog=True)
    axes.draw_frame("training step", "held-out median corner error (px)", title)
    entries = []
    for index, (name, curve) in enumerate(curves.items()):
        colour = PALETTE[index % len(PALETTE)]
        axes.polyline(curve[:, 0], curve[:, 1], colour)
        entries.append((f"{name}: {curve[-1, 1]:.2f} px at step {int(curve[-1, 0])}", colour, "line"))
    # Curves fall from the top left, so the bottom left of the plot is free for the legend.
    _legend(canvas, (92, height - 78 - 22 * len(entries)), entries)
    return canvas
