"""A part drawn small: every frame warped into a small copy of its canvas, in colour, with its mask.

OpenCV's exposure compensators and seam finders (:mod:`.gains`, :mod:`.seams`) work on every frame of a part
in one canvas. Like OpenCV's stitching sample and OpenStitching, udh runs them on a small copy (about
:data:`SMALL_MEGAPIXELS` per frame) and applies their answers at full resolution while compositing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.mosaic.inputs.frames import FrameSet
from udh_cli.mosaic.render.decoded import DecodedFrames
from udh_cli.mosaic.report import Reporter

# Per frame, as in OpenCV's stitching sample (seam_megapix 0.1): enough for brightness and seams, small enough
# that a part of hundreds of frames fits in memory.
SMALL_MEGAPIXELS = 0.1
SMALL_BUDGET_PIXELS = 10e6  # all frames of a part together at most (the seam finders take float32 copies: 120 MB)


@dataclass
class SmallPart:
    """A part drawn small: each frame warped into a copy of the canvas ``scale`` times its size.

    Attributes:
        scale: small-canvas pixels per canvas pixel.
        indices: the frames, in the order of the lists below.
        corners: (x, y) top-left of each small warped frame on the small canvas.
        images: (h, w, 3) uint8 BGR warped frames.
        masks: (h, w) uint8, 255 where the frame has pixels.
    """

    scale: float
    indices: list[int]
    corners: list[tuple[int, int]]
    images: list[np.ndarray]
    masks: list[np.ndarray]


def small_scale(frame_sizes: Sequence[tuple[int, int]], canvas_scale: float) -> float:
    """Small-canvas pixels per canvas pixel: frames of about :data:`SMALL_MEGAPIXELS` each, all together at most
    :data:`SMALL_BUDGET_PIXELS` (``canvas_scale``: canvas pixels per frame pixel)."""
    pixels = sum(w * h for w, h in frame_sizes) * canvas_scale**2
    if pixels <= 0:
        return 1.0
    per_frame = SMALL_MEGAPIXELS * 1e6 * len(frame_sizes)
    return min(1.0, math.sqrt(min(per_frame, SMALL_BUDGET_PIXELS) / pixels))


def draw_small(frameset: FrameSet, mosaic_from_frame: dict[int, np.ndarray], canvas_scale: float, reporter: Reporter,
               label: str = "small copies", decoded: DecodedFrames | None = None) -> SmallPart:
    """Every frame of a part warped into a small copy of its canvas. The full images are read once more, through
    ``decoded`` when given, which then keeps them for compositing (:mod:`.decoded`)."""
    sizes = [frameset.frames[i].size for i in mosaic_from_frame]
    scale = small_scale(sizes, canvas_scale)
    small = SmallPart(scale, [], [], [], [])
    shrink = np.diag([scale, scale, 1.0])
    with reporter.stage("small copies", len(mosaic_from_frame), label) as advance:
        for i, image in (decoded.get(list(mosaic_from_frame)) if decoded is not None else frameset.full_images(mosaic_from_frame)):
            height, width = image.shape[:2]
            small_from_frame = shrink @ mosaic_from_frame[i]
            quad = geometry.transform_points(small_from_frame, geometry.image_corners(width, height))
            x0, y0 = np.floor(quad.min(0)).astype(int)
            x1, y1 = np.ceil(quad.max(0)).astype(int) + 1
            # Shrink the frame first (area filter), then warp: the warp alone would alias at this scale.
            factor = min(1.0, 2.0 * max(x1 - x0, y1 - y0) / max(width, height))
            shrunk = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA) if factor < 1.0 else image
            from_shrunk = geometry.translation(-x0, -y0) @ small_from_frame @ geometry.resize_matrix(
                (shrunk.shape[1], shrunk.shape[0]), (width, height))
            box = (int(x1 - x0), int(y1 - y0))
            small.images.append(cv2.warpPerspective(shrunk, from_shrunk, box, flags=cv2.INTER_LINEAR))
            covered = np.full(shrunk.shape[:2], 255, np.uint8)
            if frameset.lens is not None:  # the rim a pincushion lens leaves empty
                valid = frameset.lens.valid_mask((width, height))
                covered = (cv2.resize(valid, (shrunk.shape[1], shrunk.shape[0]), interpolation=cv2.INTER_NEAREST) * 255).astype(np.uint8)
            small.masks.append(cv2.warpPerspective(covered, from_shrunk, box, flags=cv2.INTER_NEAREST))
            small.corners.append((int(x0), int(y0)))
            small.indices.append(i)
            advance(1)
    return small
