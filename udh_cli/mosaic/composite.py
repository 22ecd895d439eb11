"""Compositing: the canvas, and warping + blending frames into it one at a time (bounded memory).

Only the canvas accumulators and one full-resolution frame are in memory at once; each frame is warped
into its own bounding box on the canvas, never into a full-canvas buffer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.mosaic.frames import FrameSet
from udh_cli.mosaic.gains import apply_gain
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.seams import Seams

BLENDS = ("feather", "multiband", "none")  # the --blend choices
# Peak memory per canvas pixel while blending, accumulators and output together: the rise in peak RSS measured
# on brighton-beach's 9.3 MP canvas (it includes one 1600x900 frame's buffers, so large canvases need less).
BYTES_PER_PIXEL = {"feather": 28, "multiband": 36, "none": 20}
DEFAULT_MAX_CANVAS_BYTES = 3 * 2**30  # refuse canvases that would need more than this to blend
MULTIBAND_LEVELS = 5


@dataclass(frozen=True)
class Canvas:
    """Where a part lands: ``size`` (width, height) in pixels, ``mosaic_from_ref`` (3, 3) from reference-frame
    pixels to canvas pixels, and ``scale``, canvas pixels per reference pixel (below 1 when downscaled)."""

    size: tuple[int, int]
    mosaic_from_ref: np.ndarray
    scale: float


def plan_canvas(
    ref_from: dict[int, np.ndarray],
    sizes: Sequence[tuple[int, int]],
    blend: str,
    max_size: int | None = None,
    max_bytes: int = DEFAULT_MAX_CANVAS_BYTES,
) -> Canvas:
    """Bounds of every frame's footprint; downscaled to ``max_size`` on the longest side if given.

    Raises :class:`UdhError` when blending the canvas would take more than ``max_bytes``.
    """
    corners = np.concatenate([geometry.transform_points(h, geometry.image_corners(*sizes[i])) for i, h in ref_from.items()])
    if not np.isfinite(corners).all():
        raise UdhError("a frame's homography sends it to infinity; the estimates are broken (try another --method)")
    low = np.floor(corners.min(0))
    full = (int(np.ceil(corners[:, 0].max()) - low[0]) + 1, int(np.ceil(corners[:, 1].max()) - low[1]) + 1)
    scale = 1.0
    if max_size is not None and max(full) > max_size:
        scale = max_size / max(full)
    size = (max(1, round(full[0] * scale)), max(1, round(full[1] * scale)))
    mosaic_from_ref = geometry.resize_matrix(full, size) @ geometry.translation(-low[0], -low[1])
    needed = size[0] * size[1] * BYTES_PER_PIXEL[blend]
    if needed > max_bytes:
        fit = int(max(size) * math.sqrt(max_bytes / needed))
        raise UdhError(
            f"the mosaic canvas would be {size[0]}x{size[1]} px ({needed / 2**20:,.0f} MiB to blend, limit {max_bytes / 2**20:,.0f} MiB); "
            f"pass --max-size {fit} or smaller to downscale it"
        )
    return Canvas(size, mosaic_from_ref, scale)


def _edge_weight(size: tuple[int, int]) -> np.ndarray:
    """(h, w) float32 feather weight: 1 at the centre falling to ~0 at the border (product of tents)."""
    w, h = size
    wx = np.minimum(np.arange(w) + 1.0, w - np.arange(w)) / ((w + 1) / 2)
    wy = np.minimum(np.arange(h) + 1.0, h - np.arange(h)) / ((h + 1) / 2)
    return (wy[:, None] * wx[None, :]).astype(np.float32)


def _roi(mosaic_from_frame: np.ndarray, size: tuple[int, int], canvas: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) canvas box holding the frame's footprint, clipped; ``None`` when off the canvas."""
    quad = geometry.transform_points(mosaic_from_frame, geometry.image_corners(*size))
    x0, y0 = np.floor(quad.min(0)).astype(int) - 1
    x1, y1 = np.ceil(quad.max(0)).astype(int) + 2
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(canvas[0], x1), min(canvas[1], y1)
    return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1, y1)


def _warp(image: np.ndarray, mosaic_from_frame: np.ndarray, roi: tuple[int, int, int, int], interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    x0, y0, x1, y1 = roi
    roi_from_frame = geometry.translation(-x0, -y0) @ mosaic_from_frame
    return cv2.warpPerspective(image, roi_from_frame, (x1 - x0, y1 - y0), flags=interpolation, borderMode=cv2.BORDER_CONSTANT)


def composite(
    frames: FrameSet,
    mosaic_from_frame: dict[int, np.ndarray],
    canvas_size: tuple[int, int],
    blend: str,
    reporter: Reporter,
    label: str = "compositing",
    gains: dict[int, np.ndarray] | None = None,
    seams: Seams | None = None,
) -> np.ndarray:
    """Warp and blend the frames of one part into a (H, W, 4) BGRA uint8 canvas; alpha 255 where covered.

    ``mosaic_from_frame`` maps each frame's full-resolution pixels to canvas pixels; ``gains`` gives each
    frame's exposure gains (:func:`.gains.exposure_gains`; none: as they are). ``feather`` averages with
    weights that fall to 0 at frame borders; ``none`` and ``multiband`` first give every canvas pixel to one
    frame, then copy (``none``) or blend the seams band by band (``multiband``, OpenCV's MultiBandBlender):
    the frame whose ``seams`` mask holds the pixel (:mod:`.seams`), else the one that sees it nearest its
    centre. ``label`` names the progress bar (the time adds up under "compositing").
    """
    if blend not in BLENDS:
        raise UdhError(f"unknown blend '{blend}'; choose one of: {', '.join(BLENDS)}")
    width, height = canvas_size
    sizes = {i: frames.frames[i].size for i in mosaic_from_frame}
    weights = {size: _edge_weight(size) for size in set(sizes.values())}
    if frames.lens is not None:  # a pincushion lens's rim has no real pixels: no frame owns it there
        weights = {size: weight * frames.lens.valid_mask(size) for size, weight in weights.items()}
    rois = {i: _roi(h, sizes[i], canvas_size) for i, h in mosaic_from_frame.items()}
    rois = {i: r for i, r in rois.items() if r is not None}
    labels = None
    if blend != "feather":  # seams: the frame with the highest weight owns the pixel
        best = np.zeros((height, width), np.float32)
        labels = np.full((height, width), -1, np.int32)
        for i, roi in rois.items():
            x0, y0, x1, y1 = roi
            weight = _warp(weights[sizes[i]], mosaic_from_frame[i], roi)
            if seams is not None:  # the seam mask first; centrality (weights below 1) only where no mask holds the pixel
                weight += 2.0 * seams.in_box(i, roi) * (weight > 0)
            better = weight > best[y0:y1, x0:x1]
            best[y0:y1, x0:x1][better] = weight[better]
            labels[y0:y1, x0:x1][better] = i
        del best
    if blend == "feather":
        total = np.zeros((height, width, 3), np.float32)
        weight_sum = np.zeros((height, width), np.float32)
    elif blend == "none":
        out = np.zeros((height, width, 4), np.uint8)
    else:
        blender = cv2.detail_MultiBandBlender(0, MULTIBAND_LEVELS)
        blender.prepare((0, 0, width, height))
    with reporter.stage("compositing", len(rois), label) as advance:
        for i, image in frames.full_images(rois):
            roi = rois[i]
            x0, y0, x1, y1 = roi
            warped = _warp(image.astype(np.float32), mosaic_from_frame[i], roi)
            if gains is not None:
                warped = apply_gain(warped, gains[i])
            if blend == "feather":
                weight = _warp(weights[sizes[i]], mosaic_from_frame[i], roi)
                total[y0:y1, x0:x1] += warped * weight[..., None]
                weight_sum[y0:y1, x0:x1] += weight
            else:
                owned = labels[y0:y1, x0:x1] == i
                if blend == "none":
                    out[y0:y1, x0:x1, :3][owned] = np.clip(warped[owned] + 0.5, 0, 255).astype(np.uint8)
                    out[y0:y1, x0:x1, 3][owned] = 255
                else:
                    blender.feed(np.clip(warped, 0, 255).astype(np.int16), owned.astype(np.uint8) * 255, (x0, y0))
            advance(1)
    if blend == "feather":
        out = np.zeros((height, width, 4), np.uint8)
        strip = max(1, 2**18 // width)  # rows per strip: temporaries stay at a few MB whatever the canvas
        for top in range(0, height, strip):  # in strips, so the division needs no full-canvas temporaries
            rows = slice(top, top + strip)
            strip_weight = weight_sum[rows]
            covered = strip_weight > 1e-6
            out[rows, :, :3] = np.clip(total[rows] / np.maximum(strip_weight, 1e-6)[..., None] + 0.5, 0, 255).astype(np.uint8)
            out[rows, :, 3] = np.where(covered, 255, 0).astype(np.uint8)
            out[rows, :, :3][~covered] = 0
    elif blend == "multiband":
        result, mask = blender.blend(None, None)
        out = np.zeros((height, width, 4), np.uint8)
        out[..., :3] = np.clip(result, 0, 255).astype(np.uint8)
        out[..., 3] = np.where(mask > 0, 255, 0).astype(np.uint8)
    return out


def preview(mosaic_bgra: np.ndarray, max_side: int = 1200, background: int = 40) -> np.ndarray:
    """(h, w, 3) BGR uint8 small copy of the mosaic on a dark background, for a quick look."""
    height, width = mosaic_bgra.shape[:2]
    scale = min(1.0, max_side / max(width, height))
    small = cv2.resize(mosaic_bgra, (max(1, round(width * scale)), max(1, round(height * scale))), interpolation=cv2.INTER_AREA)
    alpha = small[..., 3:4].astype(np.float32) / 255.0
    return (small[..., :3] * alpha + background * (1 - alpha) + 0.5).astype(np.uint8)
