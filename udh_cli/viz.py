"""Pictures of results, in the style of the paper's figure 1: A's border, warped onto B."""

from __future__ import annotations

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.images import to_bgr_u8

ESTIMATE_COLOUR = (60, 220, 60)  # BGR green
TRUTH_COLOUR = (40, 40, 235)  # BGR red
A_BORDER_COLOUR = (235, 160, 40)  # BGR blue


def _polyline(panel, quad, colour, scale, thickness=2):
    """Draw ``quad`` (4, 2), in pixels of the full-size image, on ``panel``, that image shown at ``scale``.

    ``panel`` is a view into the canvas, so lines that leave the image are clipped at its edge rather than
    drawn over the other image or the caption. Points are scaled the way ``cv2.resize`` with ``fx=scale``
    moves pixel centres, and drawn with 4 bits of sub-pixel precision.
    """
    shift = 4
    points = (np.asarray(quad, dtype=np.float64) + 0.5) * scale - 0.5
    # A corner near the horizon can land at 1e12 px and overflow int32 once shifted; such a quadrilateral
    # means nothing on screen anyway, so it is clamped to +-1e7 px and drawn however it falls.
    points = np.nan_to_num(points, nan=0.0, posinf=1e7, neginf=-1e7)
    points = np.round(np.clip(points, -1e7, 1e7) * (1 << shift)).astype(np.int32)
    cv2.polylines(panel, [points.reshape(-1, 1, 2)], True, colour, thickness, cv2.LINE_AA, shift)


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
    gap = 12
    # The gap is not scaled, and cv2.resize rounds each panel's width: keep 2 px of slack for that.
    scale = min(1.0, (max_width - gap - 2) / (a.shape[1] + b.shape[1]))
    a_s = cv2.resize(a, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    b_s = cv2.resize(b, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    footer = 34
    canvas = np.full((max(a_s.shape[0], b_s.shape[0]) + footer, a_s.shape[1] + gap + b_s.shape[1], 3), 255, np.uint8)
    canvas[: a_s.shape[0], : a_s.shape[1]] = a_s
    offset_b = a_s.shape[1] + gap
    canvas[: b_s.shape[0], offset_b : offset_b + b_s.shape[1]] = b_s
    panel_a = canvas[: a_s.shape[0], : a_s.shape[1]]
    panel_b = canvas[: b_s.shape[0], offset_b : offset_b + b_s.shape[1]]
    corners_a = geometry.image_corners(a.shape[1], a.shape[0])
    _polyline(panel_a, corners_a, A_BORDER_COLOUR, scale)
    text = label
    with np.errstate(divide="ignore", invalid="ignore"):  # a corner at infinity is clamped when drawn
        quad_true = None if b_from_a_true is None else geometry.transform_points(b_from_a_true, corners_a)
        quad_estimate = None if b_from_a is None else geometry.transform_points(b_from_a, corners_a)
    if quad_true is not None:
        _polyline(panel_b, quad_true, TRUTH_COLOUR, scale, 3)
    if quad_estimate is not None:
        _polyline(panel_b, quad_estimate, ESTIMATE_COLOUR, scale)
        if b_from_a_true is not None:
            error = float(geometry.mace(b_from_a, b_from_a_true, a.shape[1], a.shape[0]))
            text += f"  corner error {error:.2f} px (green: estimate, red: truth)"
    else:
        text += "  no estimate"
    cv2.putText(canvas, text.strip(), (8, canvas.shape[0] - 11), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas
