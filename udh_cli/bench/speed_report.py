"""What ``udh bench speed`` writes: ``results.json``, ``results.md`` and ``stages.png`` (a stacked bar of the
mosaic's stages beside the reference workload, drawn with OpenCV like the other benchmark figures)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from udh_cli.bench.plots import GRID, PALETTE, TEXT, Axes, _number, _text
from udh_cli.bench.report import _png_bytes, check_output_folder
from udh_cli.bench.speed import REFERENCE_SIDE, UNSTAGED, SpeedResult
from udh_cli.errors import UdhError
from udh_cli.files import write_file_set

REFERENCE_COLOUR = (70, 70, 70)  # darker than every stage's colour
UNSTAGED_COLOUR = (215, 215, 215)


def _flight_name(result: SpeedResult) -> str:
    """The folder's last two parts: flights are often kept as NAME/images."""
    return "/".join(Path(result.folder).resolve().parts[-2:])


def _load(value: float | None) -> str:
    return "unknown" if value is None else f"{value:.2f}"


def markdown(result: SpeedResult) -> str:
    """The stage table (seconds and x reference), the run's facts and, when timed, the single pairs."""
    ref = result.reference
    lines = [f"# udh bench speed: {_flight_name(result)}, method {result.method}, workers {result.workers or 'auto'}", "",
             f"Reference: {ref.frames} frames decoded and run through SIFT at {REFERENCE_SIDE} px on one thread in "
             f"**{ref.seconds:.2f} s** on {result.machine['cpu']} ({result.machine['cpu_count']} cores, "
             f"1-minute load {_load(result.machine.get('load_average_1min_at_start'))} at the start, "
             f"{_load(result.machine.get('load_average_1min'))} at the end).", "",
             "| stage | s | x reference |", "|---|---|---|"]
    lines += [f"| {stage.name} | {stage.seconds:.2f} | {stage.ratio:.3f} |" for stage in result.stages]
    lines.append(f"| **wall** | **{result.wall_s:.2f}** | **{result.ratio:.2f}** |")
    summary, memory = result.summary, result.peak_memory_mb
    lines += ["", f"Placed {summary['placed']} of {summary['frames']} frames in {summary['parts']} part(s); "
                  f"{summary['pairs_ok']} pairs used. Peak memory {memory['self']:.0f} MiB (this process), "
                  f"{memory['children']:.0f} MiB (largest worker)."]
    if result.pairs:
        lines += ["", f"Single pairs: the first {result.pairs[0].pairs} consecutive pairs at full resolution, interleaved, "
                      "median wall time of `estimate`.", "",
                  "| method | ms/pair | x sift | answered (by) | network path's stages: median ms (pairs where it ran) |",
                  "|---|---|---|---|---|"]
        for pair in result.pairs:
            ratio = "-" if pair.sift_ratio is None else f"{pair.sift_ratio:.3f}"
            by = ", ".join(f"{stage} {n}" for stage, n in pair.answered_by.items())
            stages = ", ".join(f"{name} {ms:.1f} ({pair.stage_pairs[name]})" for name, ms in pair.stage_ms.items()) or "-"
            lines.append(f"| {pair.method} | {pair.median_ms:.1f} | {ratio} | {pair.answered}/{pair.pairs} ({by}) | {stages} |")
    return "\n".join(lines) + "\n"


def stage_bars(result: SpeedResult, size: tuple[int, int] = (760, 300)) -> np.ndarray:
    """(H, W, 3) uint8 BGR: the reference and the mosaic as horizontal bars in seconds, the mosaic's stacked by
    stage, with a legend of each stage's seconds and ratio."""
    width, height = size
    legend_rows = (len(result.stages) + 1) // 2
    canvas = np.full((height + 22 * legend_rows + 10, width, 3), 255, np.uint8)
    longest = max(result.wall_s, result.reference.seconds)
    axes = Axes(canvas, (150, 40, width - 180, height - 110), (0.0, longest * 1.05), (0.0, 2.0))
    _frame(axes, f"{_flight_name(result)}: {result.method}, {result.ratio:.2f}x the reference")
    _bar(axes, 1.5, [(result.reference.seconds, REFERENCE_COLOUR)], f"reference ({REFERENCE_SIDE} px SIFT)")
    colours = [_stage_colour(k, stage.name) for k, stage in enumerate(result.stages)]
    _bar(axes, 0.5, [(stage.seconds, colour) for stage, colour in zip(result.stages, colours)], f"mosaic ({result.method})")
    for k, (stage, colour) in enumerate(zip(result.stages, colours)):
        x, y = 20 + (k % 2) * (width // 2), height + 22 * (k // 2)
        cv2.rectangle(canvas, (x, y - 7), (x + 14, y + 7), colour, -1)
        _text(canvas, f"{stage.name}: {stage.seconds:.2f} s, {stage.ratio:.2f}x", (x + 22, y), valign="middle")
    return canvas


def _stage_colour(index: int, name: str) -> tuple[int, int, int]:
    """The palette in order, then again at half strength (runs with many loop-closure rounds); the unstaged rest
    in light grey."""
    if name == UNSTAGED:
        return UNSTAGED_COLOUR
    colour = PALETTE[index % len(PALETTE)]
    return colour if index < len(PALETTE) else tuple((c + 255) // 2 for c in colour)


def _frame(axes: Axes, title: str) -> None:
    """The plot's box, x ticks in seconds with their grid, and the title (no y ticks: the bars are labelled)."""
    left, top, width, height = axes.rect
    for x in axes._ticks(axes.xlim, False)[0]:
        px = int(axes.to_px([x], [0.0])[0, 0])
        cv2.line(axes.canvas, (px, top), (px, top + height), GRID, 1)
        _text(axes.canvas, _number(x), (px, top + height + 9), align="centre", valign="top")
    cv2.rectangle(axes.canvas, (left, top), (left + width, top + height), TEXT, 1)
    _text(axes.canvas, "seconds", (left + width // 2, top + height + 40), scale=0.5, align="centre")
    _text(axes.canvas, title, (left + width // 2, top - 10), scale=0.55, align="centre")


def _bar(axes: Axes, centre: float, segments: list[tuple[float, tuple[int, int, int]]], label: str) -> None:
    """Segments of ``(seconds, colour)`` laid end to end along x, 0.6 units tall around ``centre``."""
    start = 0.0
    for seconds, colour in segments:
        (x0, y0), (x1, y1) = axes.to_px([start, start + seconds], [centre + 0.3, centre - 0.3])
        cv2.rectangle(axes.canvas, (int(x0), int(y0)), (int(x1), int(y1)), colour, -1)
        start += seconds
    _text(axes.canvas, label, (axes.rect[0] - 8, int(axes.to_px([0.0], [centre])[0, 1])), align="right", valign="middle", colour=TEXT)


def write_speed_outputs(result: SpeedResult, out_dir: str | Path, overwrite: bool = False) -> list[Path]:
    """Write ``results.json``, ``results.md`` and ``stages.png`` into ``out_dir`` (created), all or none, replacing
    only files udh wrote unless ``overwrite``; returns their paths."""
    out_dir = check_output_folder(out_dir, overwrite)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UdhError(f"{out_dir}: cannot create the results folder ({exc.strerror}); choose another --out") from None
    return write_file_set(out_dir, {"results.json": (json.dumps(result.to_json(), indent=2) + "\n").encode(),
                                    "results.md": markdown(result).encode(),
                                    "stages.png": _png_bytes(stage_bars(result))}, overwrite)
