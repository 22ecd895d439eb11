"""Pictures of results, in the style of the paper's figure 1: A's border, warped onto B."""

from __future__ import annotations

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.images import to_bgr_u8

ESTIMATE_COLOUR = (60, 220, 60)  # BGR green
TRUTH_COLOUR = (40, 40, 235)  # BGR red
A_BORDER_COLOUR = (235, 160, 40)  # BGR blue


def _polyline(canvas, quad, colour, scale, offset_x, thickness=2):
    points = np.round((np.asarray(quad) + 0.5) * scale - 0.5 + [offset_x, 0]).astype(np.int32)
    cv2.polylines(canvas, [points.reshape(-1, 1, 2)], True, colour, thickness, cv2.LINE_AA)


def draw_estimate(
    image_a: np.ndarray,
    image_b: np.ndarray,
    b_from_a: np.ndarray | None,
    b_from_a_true: np.ndarray | None = None,
    label: str = "",
    max_width: int = 1600,
) -> np.ndarray:
    """A side-by-side picture: A with its border, and B with A's border warped by the estimate (green)
    and, if given, by the ground truth (red), with the corner error written underneath.

    Returns an (H, W, 3) uint8 BGR image at most ``max_width`` wide. A's border is drawn through the
    corner-pixel centres, the points the corner error is measured at.
    """
    a, b = to_bgr_u8(image_a), to_bgr_u8(image_b)
    height = max(a.shape[0], b.shape[0])
    gap = 12
    scale = min(1.0, max_width / (a.shape[1] + b.shape[1] + gap))
    a_s = cv2.resize(a, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    b_s = cv2.resize(b, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    footer = 34
    canvas = np.full((int(round(height * scale)) + footer, a_s.shape[1] + gap + b_s.shape[1], 3), 255, np.uint8)
    canvas[: a_s.shape[0], : a_s.shape[1]] = a_s
    offset_b = a_s.shape[1] + gap
    canvas[: b_s.shape[0], offset_b : offset_b + b_s.shape[1]] = b_s
    corners_a = geometry.image_corners(a.shape[1], a.shape[0])
    _polyline(canvas, corners_a, A_BORDER_COLOUR, scale, 0)
    text = label
    if b_from_a_true is not None:
        _polyline(canvas, geometry.transform_points(b_from_a_true, corners_a), TRUTH_COLOUR, scale, offset_b, 3)
    if b_from_a is not None:
        _polyline(canvas, geometry.transform_points(b_from_a, corners_a), ESTIMATE_COLOUR, scale, offset_b)
        if b_from_a_true is not None:
            error = float(geometry.mace(b_from_a, b_from_a_true, a.shape[1], a.shape[0]))
            text += f"  corner error {error:.2f} px (green: estimate, red: truth)"
    else:
        text += "  no estimate"
    cv2.putText(canvas, text.strip(), (8, canvas.shape[0] - 11), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas
