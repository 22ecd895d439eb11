"""The plane of a part without anchors: the ground the frames look down on, not the reference frame's view of it.

Why: without GPS or ground-control points, the global solve fixes the gauge (a homography of the mosaic plane)
by holding the reference frame at the identity, so every frame is drawn in the reference frame's own view of
the ground. Any error in the reference's perspective, or its real tilt, then bends the whole map, and the bend
grows with the distance from the reference. On a simulated 504-frame survey the solved frames agreed with the
ground to 0.84 px median after the best homography, but only to 25.9 px after the best similarity: the map was
right up to a projective warp that came from one frame.

A survey looks down on the ground, so its frames are, on average, similarities of it. The homography of the
plane that makes them so recovers the ground up to a similarity. Two linear least-squares fits find it:

1. perspective: the row ``(g, h, 1)`` that brings every frame's perspective terms, in the frame's own
   normalised coordinates, closest to zero (reweighted a few times by each frame's depth term);
2. shape: the aspect and shear that make every frame's Jacobian at its centre closest to a rotation and
   scale (conformal).

Then a similarity keeps the reference frame's centre, scale and heading where they were, so the map's units stay
reference-frame pixels near the reference. Sizes are (width, height) in full-resolution pixels.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.mosaic.solve.homographies import frame_normaliser

MIN_FRAMES = 10  # fewer frames hold too little evidence about the ground's plane: the reference's view is kept
PERSPECTIVE_ROUNDS = 5  # reweightings of the perspective fit; it had settled after 3 on the simulated surveys


def _perspective_row(ref_from: dict[int, np.ndarray], sizes: Sequence[tuple[int, int]]) -> np.ndarray:
    """(3, 3) ``[[1, 0, 0], [0, 1, 0], [g, h, 1]]`` minimising the frames' perspective terms (step 1)."""
    correction = np.eye(3)
    for _ in range(PERSPECTIVE_ROUNDS):
        rows, targets = [], []
        for i, h in ref_from.items():
            normalised = h @ np.linalg.inv(frame_normaliser(sizes[i]))
            weight = 1.0 / max(abs(float(correction[2] @ normalised[:, 2])), 1e-9)
            # Row 3 of correction @ normalised is g * n[0] + h * n[1] + n[2]; its first two entries should be 0.
            rows.append(weight * normalised[:2, :2].T)
            targets.append(-weight * normalised[2, :2])
        g, h = np.linalg.lstsq(np.concatenate(rows), np.concatenate(targets), rcond=None)[0]
        correction = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [g, h, 1.0]])
    return correction


def _conformal_shape(ref_from: dict[int, np.ndarray], sizes: Sequence[tuple[int, int]]) -> np.ndarray:
    """(3, 3) ``[[1 + a, s, 0], [0, 1, 0], [0, 0, 1]]`` making the frames' Jacobians closest to conformal (step 2)."""
    rows, targets = [], []
    for i, h in ref_from.items():
        centre = np.array([(sizes[i][0] - 1) / 2, (sizes[i][1] - 1) / 2])
        j = geometry.homography_jacobian(h, centre)
        # shape @ j is conformal when its (0,0) equals its (1,1) and its (0,1) is minus its (1,0).
        rows += [[j[0, 0], j[1, 0]], [j[0, 1], j[1, 1]]]
        targets += [j[1, 1] - j[0, 0], -j[1, 0] - j[0, 1]]
    aspect, shear = np.linalg.lstsq(np.array(rows), np.array(targets), rcond=None)[0]
    return np.array([[1.0 + aspect, shear, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def rectifying_homography(ref_from: dict[int, np.ndarray], sizes: Sequence[tuple[int, int]], reference: int,
                          max_frame_scale: float = 3.0) -> np.ndarray | None:
    """(3, 3) homography of the mosaic plane that maps it onto the ground the frames look at, up to a similarity
    that leaves the reference frame's centre, scale and heading unchanged; None when the part has fewer than
    :data:`MIN_FRAMES` frames or when the result would make a drawable frame degenerate (see
    :func:`geometry.is_valid_homography`), and the reference frame's view is kept.

    ``ref_from``: frame -> (3, 3) ``ref_from_frame`` after the global solve.
    """
    if len(ref_from) < MIN_FRAMES:
        return None
    perspective = _perspective_row(ref_from, sizes)
    shape = _conformal_shape({i: perspective @ h for i, h in ref_from.items()}, sizes)
    return keep_reference_view(shape @ perspective, ref_from, sizes, reference, max_frame_scale)


def keep_reference_view(plane: np.ndarray, ref_from: dict[int, np.ndarray], sizes: Sequence[tuple[int, int]], reference: int,
                        max_frame_scale: float = 3.0) -> np.ndarray | None:
    """``plane`` (3, 3), a homography of the mosaic plane onto the ground, followed by the similarity that keeps
    the reference frame's centre, scale and heading where they were, so that the map's units stay
    reference-frame pixels near the reference; None when the result is not finite or would make a drawable
    frame degenerate (:func:`geometry.is_valid_homography`)."""
    centre = np.array([(sizes[reference][0] - 1) / 2, (sizes[reference][1] - 1) / 2])
    at = geometry.transform_points(ref_from[reference], centre[None])[0]
    j = geometry.homography_jacobian(plane, at)
    scale_cos, scale_sin = (j[0, 0] + j[1, 1]) / 2, (j[1, 0] - j[0, 1]) / 2
    local = np.array([[scale_cos, -scale_sin, 0.0], [scale_sin, scale_cos, 0.0], [0.0, 0.0, 1.0]])
    moved = geometry.transform_points(plane, at[None])[0]
    keep = geometry.translation(*at) @ np.linalg.inv(local) @ geometry.translation(-moved[0], -moved[1])
    plane = keep @ plane
    plane /= plane[2, 2]
    if not np.isfinite(plane).all():
        return None
    for i, h in ref_from.items():  # a frame that was drawable must stay so
        if geometry.is_valid_homography(h, *sizes[i], max_scale=max_frame_scale) and \
                not geometry.is_valid_homography(plane @ h, *sizes[i], max_scale=max_frame_scale):
            return None
    return plane
