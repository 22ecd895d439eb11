"""Synthetic pairs with the motion of a real flight: any heading, scale changes, low overlap, real lighting.

The paper's generator (:mod:`udh_cli.synthetic`) perturbs the corners of a 128x128 crop by at most rho,
with no rotation and almost no scale change. Consecutive frames of a real flight turn by tens of degrees
(up to 180 at the end of a strip), change scale as the aircraft climbs, and overlap by as little as half.
This generator draws that motion, and renders both views the way the estimators see a real frame: the
whole frame resized to P x P, whatever its aspect ratio.

The procedure (pixel conventions of :mod:`udh_cli.geometry`):

1. A frame aspect ``w/h`` is drawn (square, 4:3, 3:2 or 16:9 frames are all squashed to P x P).
2. The motion ``M`` of A's frame relative to B's is drawn in the scene's isotropic pixels, in units of
   B's frame: a rotation about the frame centre, a scale, a translation, then a perspective jitter of the
   corners (``perspective`` px of the P x P view, as the paper's rho).
3. The largest frame that keeps both footprints inside the source image is placed at random, so every
   pixel of both views is real (no reflected or invented content). Draws whose views overlap by less
   than ``min_overlap`` are drawn again.
4. ``source_from_b`` maps the P x P view of B into the source; ``source_from_a = M source_from_b``. The
   patch homography ``b_from_a = source_from_b^-1 M source_from_b`` gives the 4-point ``offsets``.
5. Lighting: the paper's brightness/contrast/gamma, plus what real flights show (cloud shadows,
   vignetting, motion blur, sensor noise, JPEG artefacts), drawn independently for each view.

``context_a`` renders the source in A's view frame on a canvas of 3P x 3P with A's view at ``(P, P)``,
so that the photometric loss can look up every pixel of B that A's larger surroundings cover.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.generator_settings import MotionConfig  # defined without NumPy: the command line reads its defaults
from udh_cli.synthetic import PairBatch, _occlude, illuminate

ASPECTS = (1.0, 4.0 / 3.0, 3.0 / 2.0, 16.0 / 9.0)  # frame shapes of common drone cameras (w / h)
SOURCE_SHORT_SIDE = 360  # sources are resized to this short side (long side at most 2x): room for large motion
CONTEXT_FACTOR = 3  # context canvas side, in views: A's view sits in the middle of a 3x3 grid of views
# How the cascade's later rounds fill what lies outside A when they pre-warp it by the answer so far
# (DeepEstimator.predict_small), and how residual training pairs (MotionConfig.residual) are drawn to match.
# Reflected borders instead took the flight-motion benchmark's failures from 27.5 to 23.5 %, but real
# consecutive pairs did not follow (brighton-beach under 10 px 38 -> 25 %, copr under 3 px 85 -> 82 %;
# docs/training.md), so the edges stay replicated.
PREWARP_BORDER = cv2.BORDER_REPLICATE


def source_size(width: int, height: int) -> tuple[int, int]:
    """(w, h) a source of ``width`` x ``height`` is resized to: short side :data:`SOURCE_SHORT_SIDE`, aspect at most 2."""
    short, long_ = sorted((width, height))
    aspect = min(long_ / short, 2.0)
    big = int(round(SOURCE_SHORT_SIDE * aspect))
    return (big, SOURCE_SHORT_SIDE) if width >= height else (SOURCE_SHORT_SIDE, big)


def similarity_about(center: tuple[float, float], heading_deg: float, scale: float, shift: tuple[float, float]) -> np.ndarray:
    """(3, 3) rotation by ``heading_deg`` and scaling by ``scale`` about ``center``, then a shift; pixels."""
    t = math.radians(heading_deg)
    c, s = math.cos(t) * scale, math.sin(t) * scale
    cx, cy = center
    return np.array([[c, -s, cx - c * cx + s * cy + shift[0]], [s, c, cy - s * cx - c * cy + shift[1]], [0, 0, 1.0]])


def draw_view_motion(rng: np.random.Generator, config: MotionConfig, patch: int, aspect: float) -> np.ndarray:
    """``M`` in the frame's own isotropic pixels: a frame of ``aspect`` with height ``patch``. (3, 3).

    Applied as ``frame_from_a = M`` with B's frame the identity: A's footprint is B's frame moved by M.
    """
    width, height = patch * aspect, float(patch)
    heading = rng.uniform(-config.max_heading, config.max_heading)
    low, high = config.scale_range
    scale = math.exp(rng.uniform(math.log(low), math.log(high)))
    shift = (rng.uniform(-1, 1) * config.max_shift * width, rng.uniform(-1, 1) * config.max_shift * height)
    center = ((width - 1) / 2, (height - 1) / 2)
    return similarity_about(center, heading, scale, shift)


def _overlap(b_from_a: np.ndarray, view: tuple[int, int]) -> float:
    """Share of B's view (``(width, height)`` pixels) that A's view covers."""
    corners = geometry.image_corners(*view)
    quad = geometry.transform_points(b_from_a, corners).astype(np.float32)
    area, _ = cv2.intersectConvexConvex(quad, corners.astype(np.float32))
    return float(area) / float((view[0] - 1) * (view[1] - 1))


def _draw_geometry(rng: np.random.Generator, config: MotionConfig, view: tuple[int, int], source_wh: tuple[int, int],
                   aspect: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """One motion placed in a source: (source_from_b, source_from_a, b_from_a) of ``view``-sized views
    (``(width, height)`` pixels), or None when it does not fit. ``aspect``: the frame's width / height
    (None: drawn from :data:`ASPECTS`, either way up; a square view then squashes the frame, as the
    estimators do)."""
    view_w, view_h = view
    if aspect is None:
        aspect = float(rng.choice(ASPECTS))
        if rng.uniform() < 0.5:
            aspect = 1.0 / aspect  # portrait frames too
    # Frame coordinates: isotropic pixels of B's frame with height ``view_h``; the view scales x to its width.
    view_from_frame = np.diag([view_w / (view_h * aspect), 1.0, 1.0])
    frame_from_a_frame = draw_view_motion(rng, config, view_h, aspect)
    corners = geometry.image_corners(view_w, view_h)
    jitter = rng.uniform(-config.perspective, config.perspective, (4, 2))
    a_view_from_jittered = geometry.homography_from_points(corners + jitter, corners)  # jitter A's view corners
    # frame_from_a_view: A's view -> A's frame (unsquash) -> B's frame (M), with the corner jitter first.
    frame_from_a_view = frame_from_a_frame @ np.linalg.inv(view_from_frame) @ np.linalg.inv(a_view_from_jittered)
    b_from_a = view_from_frame @ frame_from_a_view
    if not geometry.is_valid_homography(b_from_a, view_w, view_h, max_scale=4.0) or _overlap(b_from_a, view) < config.min_overlap:
        return None
    # Bounding box of both footprints in frame units, then the largest frame size that fits the source.
    footprint = np.vstack([geometry.transform_points(np.linalg.inv(view_from_frame), corners),
                           geometry.transform_points(frame_from_a_view, corners)])
    low, high = footprint.min(0), footprint.max(0)
    extent = high - low
    sw, sh = source_wh
    fit = min((sw - 2) / extent[0], (sh - 2) / extent[1])
    if fit < 0.5:  # the views would be upsampled more than 2x: too little detail
        return None
    zoom = fit * rng.uniform(0.6, 1.0)  # source pixels per frame pixel
    free = np.array([sw - 1, sh - 1]) - extent * zoom
    offset = rng.uniform(0, 1, 2) * np.maximum(free, 0) - low * zoom
    source_from_frame = np.array([[zoom, 0, offset[0]], [0, zoom, offset[1]], [0, 0, 1.0]])
    source_from_b = source_from_frame @ np.linalg.inv(view_from_frame)
    source_from_a = source_from_frame @ frame_from_a_view
    return source_from_b, source_from_a, b_from_a


MAX_DRAWS = 1000  # a motion that fits this often fails for a reason: a source too small, an overlap too high


def _draw_until_it_fits(rng: np.random.Generator, config: MotionConfig, view: tuple[int, int], source_wh: tuple[int, int],
                        aspect: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_draw_geometry` again until a motion fits the source; :class:`UdhError` after :data:`MAX_DRAWS`."""
    for _ in range(MAX_DRAWS):
        drawn = _draw_geometry(rng, config, view, source_wh, aspect)
        if drawn is not None:
            return drawn
    raise UdhError(f"no flight motion fits a {source_wh[0]}x{source_wh[1]} source in {MAX_DRAWS} draws "
                   f"(overlap at least {config.min_overlap}); give larger images or a gentler motion")


def make_flight_frames(sources: list[np.ndarray], count: int, config: MotionConfig, rng: np.random.Generator,
                       view: tuple[int, int] = (320, 240), illumination: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whole frames with flight motion, for benchmarks: ``(frames_a, frames_b)`` (N, h, w) uint8 grey and the
    true ``b_from_a`` (N, 3, 3) in their pixels. The frames keep ``view``'s aspect (no squash), and get the
    same lighting as training pairs. Deterministic given ``rng``'s state."""
    width, height = view
    frames_a = np.empty((count, height, width), np.uint8)
    frames_b = np.empty((count, height, width), np.uint8)
    truths = np.empty((count, 3, 3))
    for i in range(count):
        image = sources[int(rng.integers(0, len(sources)))].astype(np.float32) / 255.0
        source_from_b, source_from_a, truths[i] = _draw_until_it_fits(rng, config, view, (image.shape[1], image.shape[0]), width / height)
        views = []
        for source_from_view in (source_from_a, source_from_b):
            seen = cv2.warpPerspective(image, source_from_view, view, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                       borderMode=cv2.BORDER_REPLICATE)
            if illumination:
                seen = illuminate(seen, rng)
            if config.lighting > 0:
                seen = flight_lighting(seen, rng, config.lighting)
            views.append(np.clip(seen * 255.0 + 0.5, 0, 255).astype(np.uint8))
        frames_a[i], frames_b[i] = views
    return frames_a, frames_b, truths


def flight_lighting(view: np.ndarray, rng: np.random.Generator, probability: float) -> np.ndarray:
    """Real-flight photometric effects on an (H, W) float view in [0, 1], each with ``probability``.

    Cloud shadows (a soft dark blob), vignetting (radial fall-off), motion blur (a short line kernel),
    sensor noise, and JPEG re-encoding at a low quality. Grey views have no white balance of their own; a
    colour cast reaches grey as the brightness and gamma shifts that :func:`illuminate` already draws.
    """
    out = view.astype(np.float32, copy=True)
    height, width = out.shape
    size = min(height, width)
    if rng.uniform() < probability:
        mask = np.zeros_like(out)
        x, y = rng.integers(-size // 4, size + size // 4, 2)
        centre = (int(x * width / size), int(y * height / size))
        axes = tuple(int(v) for v in rng.integers(size // 6, size // 1.5, 2))
        cv2.ellipse(mask, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1.0, -1)
        mask = cv2.GaussianBlur(mask, (0, 0), size / 16)
        out *= 1.0 - rng.uniform(0.25, 0.6) * mask
    if rng.uniform() < probability:
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
        r2 = ((xx - (width - 1) / 2) ** 2 + (yy - (height - 1) / 2) ** 2) / (size / 2) ** 2
        out *= 1.0 - rng.uniform(0.1, 0.4) * np.clip(r2 / 2.0, 0, 1)
    if rng.uniform() < probability:
        length = int(rng.integers(3, 8))
        kernel = np.zeros((length, length), np.float32)
        kernel[length // 2, :] = 1.0 / length
        rotation = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), float(rng.uniform(0, 180)), 1.0)
        kernel = cv2.warpAffine(kernel, rotation, (length, length))
        out = cv2.filter2D(out, -1, kernel / max(kernel.sum(), 1e-6), borderType=cv2.BORDER_REFLECT)
    if rng.uniform() < probability:
        out = out + rng.normal(0, rng.uniform(0.005, 0.03), out.shape).astype(np.float32)
    out = np.clip(out, 0.0, 1.0)
    if rng.uniform() < probability:
        quality = int(rng.integers(25, 85))
        ok, encoded = cv2.imencode(".jpg", (out * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, quality])
        if ok:
            out = cv2.imdecode(encoded, cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0
    return out


def make_motion_pairs(sources: list[np.ndarray], count: int, config: MotionConfig, rng: np.random.Generator,
                      patch: int = 128, small_motion_fraction: float = 0.0, illumination: bool = True,
                      occluders: float = 0.0, with_context: bool = True) -> PairBatch:
    """Draw ``count`` pairs of flight motion from ``sources`` (grey uint8 images of any size, see :func:`source_size`).

    Deterministic given ``rng``'s state. Returns the same :class:`~udh_cli.synthetic.PairBatch` as the
    paper's generator, with ``context_a`` on a 3P x 3P canvas and ``origin`` = (P, P).
    """
    side = patch * CONTEXT_FACTOR
    patch_a = np.empty((count, patch, patch), np.float32)
    patch_b = np.empty((count, patch, patch), np.float32)
    clean_b = np.empty((count, patch, patch), np.float32)
    offsets = np.empty((count, 4, 2), np.float32)
    origin = np.full((count, 2), float(patch), np.float32)
    context = np.empty((count, 2, side, side), np.float32) if with_context else np.zeros((count, 2, 1, 1), np.float32)
    index = rng.integers(0, len(sources), count)
    ones = None
    for i in range(count):
        image = sources[index[i]]
        h, w = image.shape
        amount = rng.uniform() if rng.uniform() < small_motion_fraction else 1.0
        motion = config.scaled(amount) if amount < 1.0 else config
        source_from_b, source_from_a, b_from_a = _draw_until_it_fits(rng, motion, (patch, patch), (w, h))
        prewarp = None
        if config.residual > 0:
            # A later round sees A warped by an answer that is off by ``left``: b_from_a = left . prewarp.
            corners = geometry.image_corners(patch, patch)
            left = geometry.homography_from_points(corners, corners + rng.uniform(-config.residual, config.residual, (4, 2)))
            prewarp = np.linalg.inv(left) @ b_from_a
            source_from_a, b_from_a = source_from_a @ np.linalg.inv(prewarp), left
        offsets[i] = geometry.offsets_from_homography(b_from_a, patch, patch)
        image_f = image.astype(np.float32) / 255.0
        b = cv2.warpPerspective(image_f, source_from_b, (patch, patch), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_REPLICATE)
        # A's own frame (pre-warped below when training a later round), and its lighting, as the frame has it.
        a = cv2.warpPerspective(image_f, source_from_a if prewarp is None else source_from_a @ prewarp, (patch, patch),
                                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
        if with_context:
            source_from_canvas = source_from_a @ geometry.translation(-patch, -patch)
            context[i, 0] = cv2.warpPerspective(image_f, source_from_canvas, (side, side), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                                borderMode=cv2.BORDER_REPLICATE)
            if ones is None or ones.shape != image_f.shape:
                ones = np.ones_like(image_f)
            context[i, 1] = cv2.warpPerspective(ones, source_from_canvas, (side, side), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                                borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        clean_b[i] = b
        a_seen, b_seen = a, b
        if illumination:
            a_seen, b_seen = illuminate(a_seen, rng), illuminate(b_seen, rng)
        if config.lighting > 0:
            a_seen, b_seen = flight_lighting(a_seen, rng, config.lighting), flight_lighting(b_seen, rng, config.lighting)
        if occluders >= 1.0 or (occluders > 0.0 and rng.uniform() < occluders):
            a_seen, b_seen = _occlude(a_seen, rng), _occlude(b_seen, rng)
        if prewarp is not None:
            a_seen = cv2.warpPerspective(a_seen, prewarp, (patch, patch), flags=cv2.INTER_LINEAR, borderMode=PREWARP_BORDER)
        patch_a[i], patch_b[i] = a_seen, b_seen
    return PairBatch(patch_a, patch_b, offsets, context, clean_b, origin, index)
