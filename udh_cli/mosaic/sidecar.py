"""The sidecar (``NAME.json``): what a run did, written once at the end from the stages' results."""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from udh_cli.version import __version__
from udh_cli.estimators import Estimator
from udh_cli.mosaic.config import MosaicConfig
from udh_cli.mosaic.georef.place import PartOnCanvas
from udh_cli.mosaic.inputs.frames import FrameSet
from udh_cli.mosaic.outputs.staging import SIDECAR_FORMAT
from udh_cli.mosaic.pairs.cache import estimator_identity
from udh_cli.mosaic.pairs.types import PairResult
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.solve.homographies import summarise
from udh_cli.mosaic.render.canvases import CanvasPlan, DrawnPart, PlannedPart
from udh_cli.mosaic.solve.truth import corner_errors_vs_truth, map_shape_errors, summarise_truth


def build_sidecar(frameset: FrameSet, plan: CanvasPlan, drawn: list[DrawnPart], on_map: list[PartOnCanvas], pairs: list[PairResult],
                  loops: dict[str, Any], truth: dict | None, config: MosaicConfig, opinions: Sequence[Estimator], reporter: Reporter,
                  folder: Path) -> dict[str, Any]:
    """The sidecar's content, from the stages' results; its paths are relative to ``folder``, where it is written.
    ``on_map``: the drawn parts as placed on their canvases (:func:`.render.canvases.on_canvas`)."""
    method, fallback = opinions[0], (opinions[1] if len(opinions) > 1 else None)
    frames = frameset.frames
    part_of = {i: part for part in plan.parts for i in part.frames}
    gains = {i: gain for part in drawn for i, gain in part.gains.items()}  # per placed frame, its mean gain per channel (B, G, R)
    on_canvas = {i: m for part in on_map for i, m in part.mosaic_from_frame.items()}
    records = []
    for frame in frames:
        part = part_of.get(frame.index)
        placed = part is not None
        reason = None if placed else plan.dropped.get(frame.index) or _unplaced_reason(frame.index, pairs, frames)
        if not placed:
            reporter.warn(f"{frame.name} is not in any mosaic: {reason}")
        records.append(
            {
                "index": frame.index,
                "file": frame.name,
                "width": frame.size[0],
                "height": frame.size[1],
                "status": "placed" if placed else "unplaced",
                "reason": reason,
                "part": part.number if placed else None,
                "gain": float(np.mean(gains.get(frame.index, [1.0]))),
                "gain_bgr": gains.get(frame.index),
                "metadata": None if frame.metadata is None else frame.metadata.to_json(),
                "mosaic_from_frame": on_canvas[frame.index].tolist() if placed else None,
                # --solve camera: how far the frame's camera looked from straight down (a check on oblique frames)
                "tilt_deg": part.part.cameras.tilt_deg.get(frame.index) if placed and part.part.cameras is not None else None,
            }
        )
    multi = plan.parts
    if len(multi) > 1:
        reporter.warn(f"the sequence is split into {len(multi)} parts, each written on its own: {', '.join(p.file.name for p in multi)}")
    report: dict[str, Any] = {
        "format": SIDECAR_FORMAT,
        "udh_version": __version__,
        "source": relative_to(frameset.source, folder),
        "method": method.name,
        "method_settings": estimator_identity(method)["settings"],  # with the mosaic's defaults (search)
        "fallback": None if fallback is None else fallback.name,
        "fallback_settings": None if fallback is None else estimator_identity(fallback)["settings"],
        "config": {k: v for k, v in asdict(config).items() if k not in ("method", "fallback")},
        # 16-bit or float frames: the grey range drawn as 0-255 in the 8-bit mosaic (fractions of the type's maximum)
        "display_range": None if frameset.value_range is None else {"low": frameset.value_range[0], "high": frameset.value_range[1]},
        # the lens every frame was undistorted by, and (--camera estimate) how it was fitted
        "camera": None if frameset.lens is None and frameset.lens_fit is None else
                  {**(frameset.lens.to_json() if frameset.lens is not None else {}), "estimated": frameset.lens_fit},
        "parts": [_part_record(d.plan, d.preview, folder) for d in drawn],
        "frames": records,
        "skipped_files": frameset.skipped,
        "pairs": [p.to_json() for p in pairs],
        "loop_consistency": loops,
        "summary": {
            "frames": len(frames),
            "placed": sum(r["status"] == "placed" for r in records),
            "unplaced": sum(r["status"] != "placed" for r in records),
            "skipped_files": len(frameset.skipped),
            "parts": len(multi),
            "pairs_ok": sum(p.ok for p in pairs),
            "pairs_failed": sum(p.status == "failed" for p in pairs),
            "pairs_rejected": sum(p.status == "rejected" for p in pairs),
            "gps_pairs_joined": sum(p.ok and p.kind == "gps" for p in pairs),
        },
        "warnings": reporter.warnings,
        "timings_s": dict(reporter.timings_s),
    }
    if truth is not None:
        before, after, shape = {}, {}, {}
        for p in multi:
            before.update(corner_errors_vs_truth(frames, p.part.reference, {i: p.part.chained[i] for i in p.frames}, truth))
            after.update(corner_errors_vs_truth(frames, p.part.reference, {i: p.part.solved[i] for i in p.frames}, truth))
            shape.update(map_shape_errors(frames, {i: p.part.solved[i] for i in p.frames}, truth))
        report["ground_truth_error"] = {
            "measure": "corner distance of frame->reference homographies vs the truth, reference-frame pixels",
            "chained": summarise_truth(before),
            "solved": summarise_truth(after),
            "per_frame_solved": {frames[i].name: v for i, v in sorted(after.items())},
            "map_shape": {"measure": "corner distance on the mosaic plane from the true ground positions after the best similarity, "
                                     "ground pixels, per frame", **summarise(list(shape.values()))},
        }
    return report


def _part_record(plan: PlannedPart, preview: Path | None, folder: Path) -> dict[str, Any]:
    """One drawn part as the sidecar lists it."""
    part = plan.part
    return {
        "part": plan.number,
        "file": relative_to(plan.file, folder),
        "preview": None if preview is None else relative_to(preview, folder),
        "width": plan.canvas.size[0],
        "height": plan.canvas.size[1],
        "scale": plan.canvas.scale,
        "reference_frame": part.reference,
        "plane": ("ground (camera model)" if part.cameras is not None else "ground (rectified)") if part.rectified else "reference frame",
        # --solve camera: the shared focal length and how far each camera looked from straight down
        "cameras": None if part.cameras is None else {
            "focal_px": part.cameras.focal_px,
            "focal_source": part.focal_source,
            "tilt_deg": {"median": float(np.median([part.cameras.tilt_deg[i] for i in plan.frames])),
                         "max": max(part.cameras.tilt_deg[i] for i in plan.frames)},
        },
        "frames": plan.frames,
    }


def _unplaced_reason(index: int, pairs: list[PairResult], frames) -> str:
    tried = [p for p in pairs if index in (p.a, p.b)]
    reasons = "; ".join(f"{frames[p.a].name}->{frames[p.b].name}: {p.reason}" for p in tried[:3])
    return f"no pair with it succeeded ({reasons})" if tried else "it has no neighbouring frame"


def relative_to(path: Path, folder: Path) -> str:
    """``path`` as the sidecar records it: relative to the sidecar's folder (the mosaic can move with its
    files), absolute only where no relative path exists (another drive)."""
    try:
        return os.path.relpath(Path(path).absolute(), Path(folder).absolute())
    except ValueError:
        return str(Path(path).absolute())
