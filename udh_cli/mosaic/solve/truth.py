"""Mosaic accuracy against the simulator's ground truth (:mod:`udh_cli.simulate`).

Two measures:

- **Frame to reference** (:func:`corner_errors_vs_truth`): a mosaic is only defined up to a homography of its
  plane (the gauge), so this compares frame-to-reference homographies, the estimated
  ``inv(plane_from_ref) @ plane_from_frame`` against the true ``inv(ground_from_ref) @ ground_from_frame``, as
  the distance between where each puts the frame's four corners, in reference-frame pixels. It does not
  depend on the plane the map is drawn on, the canvas offset or any ``--max-size`` downscale, and it carries
  the reference frame's own error to every frame, growing with the distance from it.
- **Map shape** (:func:`map_shape_errors`): what a map is judged by. Every frame's corners on the mosaic plane
  against their true places on the ground, after the one best similarity (scale, turn, shift) between the
  two, in ground pixels.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.mosaic.inputs.frames import Frame
from udh_cli.mosaic.georef.gps import fit_similarity
from udh_cli.simulate import GROUND_TRUTH_FILE, load_ground_truth


def corner_errors_vs_truth(frames: Sequence[Frame], reference: int, ref_from: dict[int, np.ndarray], truth: dict) -> dict[int, dict[str, float]]:
    """frame index -> {"mean_corner_px", "max_corner_px"} for the frames of one part found in ``truth``."""
    ground_from = truth["ground_from_frame"]
    if frames[reference].name not in ground_from:
        return {}
    ref_from_ground = geometry.invert(ground_from[frames[reference].name])
    ref_from_plane = geometry.invert(ref_from[reference])
    out = {}
    for i, plane_from_frame in ref_from.items():
        if frames[i].name not in ground_from:
            continue
        estimated = ref_from_plane @ plane_from_frame
        estimated /= estimated[2, 2]
        true = ref_from_ground @ ground_from[frames[i].name]
        errors = geometry.corner_errors(estimated, true / true[2, 2], *frames[i].size)
        out[i] = {"mean_corner_px": float(errors.mean()), "max_corner_px": float(errors.max())}
    return out


def map_shape_errors(frames: Sequence[Frame], plane_from: dict[int, np.ndarray], truth: dict) -> dict[int, float]:
    """frame index -> mean distance, ground pixels, of its corners on the mosaic plane (``plane_from``: frame ->
    ``plane_from_frame``) from their true ground positions, after the least-squares similarity from plane to ground."""
    ground_from = truth["ground_from_frame"]
    known = [i for i in plane_from if frames[i].name in ground_from]
    if len(known) < 2:
        return {}
    corners = {i: geometry.image_corners(*frames[i].size) for i in known}
    on_plane = np.concatenate([geometry.transform_points(plane_from[i], corners[i]) for i in known])
    on_ground = np.concatenate([geometry.transform_points(ground_from[frames[i].name], corners[i]) for i in known])
    # georef.fit_similarity maps y-down pixels to y-up metres; flipping the ground's y makes it a plain similarity.
    flip = np.diag([1.0, -1.0, 1.0])
    ground_from_plane = flip @ fit_similarity(on_plane, on_ground * [1.0, -1.0])
    distances = np.linalg.norm(geometry.transform_points(ground_from_plane, on_plane) - on_ground, axis=1).reshape(len(known), -1)
    return {i: float(d.mean()) for i, d in zip(known, distances)}


def summarise_truth(per_frame: dict[int, dict[str, float]]) -> dict[str, float | int | None]:
    """frames compared, mean of the mean corner errors, and the largest corner error of any frame."""
    if not per_frame:
        return {"frames": 0, "mean_corner_px": None, "max_corner_px": None}
    means = [v["mean_corner_px"] for v in per_frame.values()]
    return {"frames": len(per_frame), "mean_corner_px": float(np.mean(means)), "max_corner_px": float(max(v["max_corner_px"] for v in per_frame.values()))}


def load_truth(source: Path, ground_truth: str | Path | None) -> dict | None:
    """The simulator's ground truth: ``ground_truth`` when given, else ``SOURCE/ground_truth.json`` when there is one."""
    if ground_truth is not None:
        return load_ground_truth(ground_truth)
    auto = source / GROUND_TRUTH_FILE
    return load_ground_truth(auto) if source.is_dir() and auto.is_file() else None
