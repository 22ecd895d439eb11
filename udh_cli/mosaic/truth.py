"""Mosaic accuracy against the simulator's ground truth (:mod:`udh_cli.simulate`).

A mosaic is only defined up to a homography of its plane (the gauge), and udh anchors it at the
reference frame of each part. So the comparison is between frame-to-reference homographies:
estimated ``ref_from_frame`` against the true ``inv(ground_from_ref) @ ground_from_frame``, measured as
the distance between where each puts the frame's four corners, in reference-frame pixels. It does not
depend on the canvas offset or on any ``--max-size`` downscale.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.mosaic.frames import Frame


def corner_errors_vs_truth(frames: Sequence[Frame], reference: int, ref_from: dict[int, np.ndarray], truth: dict) -> dict[int, dict[str, float]]:
    """frame index -> {"mean_corner_px", "max_corner_px"} for the frames of one part found in ``truth``."""
    ground_from = truth["ground_from_frame"]
    if frames[reference].name not in ground_from:
        return {}
    ref_from_ground = geometry.invert(ground_from[frames[reference].name])
    out = {}
    for i, estimated in ref_from.items():
        if frames[i].name not in ground_from:
            continue
        true = ref_from_ground @ ground_from[frames[i].name]
        errors = geometry.corner_errors(estimated, true / true[2, 2], *frames[i].size)
        out[i] = {"mean_corner_px": float(errors.mean()), "max_corner_px": float(errors.max())}
    return out


def summarise_truth(per_frame: dict[int, dict[str, float]]) -> dict[str, float | int | None]:
    """frames compared, mean of the mean corner errors, and the largest corner error of any frame."""
    if not per_frame:
        return {"frames": 0, "mean_corner_px": None, "max_corner_px": None}
    means = [v["mean_corner_px"] for v in per_frame.values()]
    return {"frames": len(per_frame), "mean_corner_px": float(np.mean(means)), "max_corner_px": float(max(v["max_corner_px"] for v in per_frame.values()))}
