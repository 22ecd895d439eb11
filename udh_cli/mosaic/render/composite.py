"""Compositing: the canvas, and warping + blending frames into it tile by tile (bounded memory).

The canvas is blended in tiles of at most :data:`TILE_SIDE` a side (:func:`tile_boxes`), each with a margin that multiband blending needs to
see across the tile's edge, and each tile only from the frames that reach it. Only one tile's accumulators and
a few decoded frames are in memory at once, so the working set depends on the tile and frame sizes, not on the
map's area: :func:`composite_tiles` yields the tiles for a writer that streams them to a file, and
:func:`composite` assembles them into one (H, W, 4) array (4 bytes per canvas pixel).
"""

from __future__ import annotations

import math
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Iterable, Iterator, Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.mosaic.inputs.frames import FrameSet
from udh_cli.mosaic.render.decoded import DecodedFrames
from udh_cli.mosaic.render.gains import apply_gain
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.render.seams import Seams

BLENDS = ("feather", "multiband", "none")  # the --blend choices
# Peak memory per pixel of a tile (with its margin) while blending, accumulators and output together: the rise in
# peak RSS measured on a 9.3 MP region blended at once (brighton-beach's canvas; it includes one 1600x900 frame's
# buffers). A video's canvas is blended in one tile (composite_tiles), so it costs this much per canvas pixel.
BYTES_PER_PIXEL = {"feather": 28, "multiband": 36, "none": 20}
OUTPUT_BYTES_PER_PIXEL = 4  # an assembled BGRA canvas (PNG and JPEG outputs are encoded from it whole)
DEFAULT_MAX_CANVAS_BYTES = 3 * 2**30  # refuse canvases whose assembled image would need more than this
MULTIBAND_LEVELS = 5
TILE_SIDE = 2048  # canvas pixels per tile side at most; a canvas that fits in one tile is blended whole
TILE_ALIGN = 2**MULTIBAND_LEVELS  # tile corners on multiples of this: the multiband blender's coarsest grid
# Canvas pixels each tile also blends beyond its edges, then drops. Multiband blending mixes each band over a
# reach that doubles per level: the coarsest level's 5x5 kernel spans 4 * 2^MULTIBAND_LEVELS px, and the tiled
# result stays within a grey level or so of the canvas blended whole (tests/mosaic/render/test_composite.py; a
# wider margin costs more blending for a few pixels in ten thousand: docs/benchmarks.md, "The blender's reach and
# the COG's threads").
TILE_MARGIN = {"feather": 0, "none": 0, "multiband": 4 * 2**MULTIBAND_LEVELS}
# A streamed canvas costs no memory, but one this large (64k x 64k) comes from a homography gone astray, not a survey.
MAX_STREAMED_PIXELS = 2**32
# Canvas pixels of a frame fed to the multiband blender beyond those it owns: its bands reach as far as a tile's
# margin does, so the frame cut there blends as the whole frame does, within 1 grey level (tests/mosaic/render/test_composite.py).
FEED_MARGIN = TILE_MARGIN["multiband"]
TRUNCATE = 0.498  # subtracted before rounding, so that rounding truncates; under 0.5, so that whole values stay


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
    assembled: bool = True,
    one_tile: bool = False,
) -> Canvas:
    """Bounds of every frame's footprint; downscaled to ``max_size`` on the longest side if given.

    ``assembled``: the mosaic is held whole (4 bytes per pixel) to be encoded, as PNG and JPEG outputs are;
    False when its tiles stream to a file (a tiled TIFF), so its area costs no memory. ``one_tile``: the
    canvas is blended whole (a video's frames, see :func:`composite_tiles`), at :data:`BYTES_PER_PIXEL`.

    Raises :class:`UdhError` when the canvas would take more than ``max_bytes``.
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
    pixels = size[0] * size[1]
    needed = pixels * (BYTES_PER_PIXEL[blend] if one_tile else OUTPUT_BYTES_PER_PIXEL if assembled else 0)
    if needed > max_bytes:
        fit = int(max(size) * math.sqrt(max_bytes / needed))
        streamed = "" if one_tile else ", or write a .tif, whose tiles stream to the file"
        raise UdhError(
            f"the mosaic canvas would be {size[0]}x{size[1]} px ({needed / 2**20:,.0f} MiB to {'blend' if one_tile else 'hold'}, "
            f"limit {max_bytes / 2**20:,.0f} MiB); pass --max-size {fit} or smaller to downscale it{streamed}"
        )
    if pixels > MAX_STREAMED_PIXELS:
        fit = int(max(size) * math.sqrt(MAX_STREAMED_PIXELS / pixels))
        raise UdhError(f"the mosaic canvas would be {size[0]}x{size[1]} px, more than a survey's homographies place sensibly; "
                       f"check the estimates, or pass --max-size {fit} or smaller")
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


def composite_tiles(
    frames: FrameSet,
    mosaic_from_frame: dict[int, np.ndarray],
    canvas_size: tuple[int, int],
    blend: str,
    reporter: Reporter,
    label: str = "compositing",
    gains: dict[int, np.ndarray] | None = None,
    seams: Seams | None = None,
    tile_side: int | None = None,
    workers: int = 1,
    decoded: DecodedFrames | None = None,
) -> Iterator[tuple[tuple[int, int, int, int], np.ndarray]]:
    """Warp and blend the frames of one part, tile by tile: yields ``((x0, y0, x1, y1), (h, w, 4) BGRA uint8)``
    per canvas tile in row-major order; alpha 255 where covered.

    ``mosaic_from_frame`` maps each frame's full-resolution pixels to canvas pixels; ``gains`` gives each
    frame's exposure gains (:func:`.gains.exposure_gains`; none: as they are). ``feather`` averages with
    weights that fall to 0 at frame borders; ``none`` and ``multiband`` first give every canvas pixel to one
    frame, then copy (``none``) or blend the seams band by band (``multiband``, OpenCV's MultiBandBlender):
    the frame whose ``seams`` mask holds the pixel (:mod:`.seams`), else the one that sees it nearest its
    centre. Every rule is per pixel except multiband's, which each tile blends with :data:`TILE_MARGIN` more
    canvas around it. ``label`` names the progress bar (the time adds up under "compositing"); ``tile_side``:
    canvas pixels per tile side (None: :data:`TILE_SIDE`); ``workers``: tiles blended at once, in threads
    (OpenCV's warps and blender release the GIL), at most that many held beyond the one yielded; ``decoded``:
    full-resolution frames already decoded (:mod:`.decoded`, e.g. by :func:`.small.draw_small`; none: a new cache).
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
    # A video is decoded sequentially from its start on every read, so it is blended in one tile.
    side = max(width, height) if frames.is_video else (tile_side or TILE_SIDE)
    tiles = tile_boxes(width, height, side)
    margin = TILE_MARGIN[blend] if len(tiles) > 1 else 0
    plan = []  # per tile: its box, the region blended for it, and the frames reaching that region
    for tx0, ty0, tx1, ty1 in tiles:
        region = (max(0, tx0 - margin), max(0, ty0 - margin), min(width, tx1 + margin), min(height, ty1 + margin))
        plan.append(((tx0, ty0, tx1, ty1), region, {i: box for i, roi in rois.items() if (box := _intersect(roi, region)) is not None}))
    workers = max(1, min(workers, len(plan)))
    decoded = DecodedFrames(frames) if decoded is None else decoded  # shared by the threads: neighbouring tiles, blended at once, need the same frames

    # The progress counts frames blended into tiles, so that a canvas of one tile still shows its progress.
    with reporter.stage("compositing", sum(len(inside) for _, _, inside in plan), label) as advance:

        def blend_tile(step):
            (tx0, ty0, tx1, ty1), region, inside = step
            blended = _blend_region(decoded, inside, mosaic_from_frame, region, blend, weights, sizes, gains, seams, advance)
            rx0, ry0 = region[:2]
            return (tx0, ty0, tx1, ty1), np.ascontiguousarray(blended[ty0 - ry0 : ty1 - ry0, tx0 - rx0 : tx1 - rx0])

        if workers == 1:
            yield from map(blend_tile, plan)
            return
        with ThreadPoolExecutor(workers, thread_name_prefix="udh-composite") as pool:
            running: deque = deque()
            for step in plan:
                running.append(pool.submit(blend_tile, step))
                if len(running) >= workers:
                    yield running.popleft().result()
            while running:
                yield running.popleft().result()


def tile_boxes(width: int, height: int, max_side: int) -> list[tuple[int, int, int, int]]:
    """Row-major ``(x0, y0, x1, y1)`` tiles covering a ``width`` x ``height`` canvas, at most ``max_side`` a side: as
    few as that allows, of even sizes, their corners on multiples of :data:`TILE_ALIGN` where ``max_side`` allows.
    Why even: a thin last row or column of tiles costs as much blending as a whole one (each frame reaching it is
    warped and fed again, with the margin on every side); why aligned: the blender's coarsest grid then lies as it
    does on the whole canvas, and tiles blend as the canvas does (within one grey level)."""

    def spans(length: int) -> list[tuple[int, int]]:
        count = math.ceil(length / max_side)
        step = math.ceil(length / count)
        if max_side >= TILE_ALIGN:
            step = min(max_side // TILE_ALIGN * TILE_ALIGN, math.ceil(step / TILE_ALIGN) * TILE_ALIGN)
        return [(start, min(start + step, length)) for start in range(0, length, step)]

    return [(x0, y0, x1, y1) for y0, y1 in spans(height) for x0, x1 in spans(width)]


def composite(frames: FrameSet, mosaic_from_frame: dict[int, np.ndarray], canvas_size: tuple[int, int], blend: str,
              reporter: Reporter, **options) -> np.ndarray:
    """The tiles of :func:`composite_tiles` (``options``: its ``label``, ``gains``, ``seams``, ``tile_side``)
    assembled into one (H, W, 4) BGRA uint8 canvas."""
    return assemble(composite_tiles(frames, mosaic_from_frame, canvas_size, blend, reporter, **options), canvas_size)


def assemble(tiles: Iterable[tuple[tuple[int, int, int, int], np.ndarray]], canvas_size: tuple[int, int]) -> np.ndarray:
    """``((x0, y0, x1, y1), tile)`` pairs put together into one (H, W, 4) BGRA uint8 canvas of ``canvas_size`` (w, h)."""
    width, height = canvas_size
    out = np.zeros((height, width, 4), np.uint8)
    for (x0, y0, x1, y1), tile in tiles:
        out[y0:y1, x0:x1] = tile
    return out


def _intersect(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> tuple[int, int, int, int] | None:
    x0, y0, x1, y1 = max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3])
    return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1, y1)


def _blend_region(decoded: DecodedFrames, boxes: dict[int, tuple[int, int, int, int]], mosaic_from_frame: dict[int, np.ndarray],
                  region: tuple[int, int, int, int], blend: str, weights: dict[tuple[int, int], np.ndarray],
                  sizes: dict[int, tuple[int, int]], gains: dict[int, np.ndarray] | None, seams: Seams | None,
                  advance=lambda n=1: None) -> np.ndarray:
    """The canvas ``region`` (x0, y0, x1, y1) blended from the frames whose canvas ``boxes`` (inside it) are
    given: (h, w, 4) BGRA uint8. ``weights``: per frame size (w, h), the (h, w) float32 feather weight;
    ``sizes``: each frame's (w, h); ``gains``: each frame's exposure gains (:mod:`.gains`). ``advance(1)`` is
    called per frame blended."""
    rx0, ry0, rx1, ry1 = region
    width, height = rx1 - rx0, ry1 - ry0
    region_from_mosaic = geometry.translation(-rx0, -ry0)
    local = {i: (x0 - rx0, y0 - ry0, x1 - rx0, y1 - ry0) for i, (x0, y0, x1, y1) in boxes.items()}
    to_region = {i: region_from_mosaic @ mosaic_from_frame[i] for i in boxes}
    labels = None
    if blend != "feather":  # seams: the frame with the highest weight owns the pixel
        best = np.zeros((height, width), np.float32)
        labels = np.full((height, width), -1, np.int16 if max(local, default=0) < 2**15 else np.int32)  # int16: half the traffic
        for i, box in local.items():
            x0, y0, x1, y1 = box
            weight = _warp(weights[sizes[i]], to_region[i], box)
            if seams is not None:  # the seam mask first; centrality (weights below 1) only where no mask holds the pixel
                np.add(weight, 2.0, out=weight, where=seams.in_box(i, boxes[i]) & (weight > 0))
            better = weight > best[y0:y1, x0:x1]
            np.copyto(best[y0:y1, x0:x1], weight, where=better)  # copyto: no copies of the selected pixels
            np.copyto(labels[y0:y1, x0:x1], i, where=better)
        del best
    if blend == "feather":
        total = np.zeros((height, width, 3), np.float32)
        weight_sum = np.zeros((height, width), np.float32)
    elif blend == "none":
        out = np.zeros((height, width, 4), np.uint8)
    else:
        blender = cv2.detail_MultiBandBlender(0, MULTIBAND_LEVELS)
        blender.prepare((0, 0, width, height))
        fed = 0
    for i, image in decoded.get(list(local)):
        box = local[i]
        x0, y0, x1, y1 = box
        if blend == "multiband":
            fed += _feed(blender, image, to_region[i], box, labels[y0:y1, x0:x1] == i, gains[i] if gains is not None else None)
            advance(1)
            continue
        # Warped as uint8, then made float: a quarter of the memory traffic of converting the whole frame first.
        warped = _warp(image, to_region[i], box).astype(np.float32)
        if gains is not None:
            warped = apply_gain(warped, gains[i])
        if blend == "feather":
            weight = _warp(weights[sizes[i]], to_region[i], box)
            total[y0:y1, x0:x1] += warped * weight[..., None]
            weight_sum[y0:y1, x0:x1] += weight
        else:
            owned = labels[y0:y1, x0:x1] == i
            out[y0:y1, x0:x1, :3][owned] = np.clip(warped[owned] + 0.5, 0, 255).astype(np.uint8)
            out[y0:y1, x0:x1, 3][owned] = 255
        advance(1)
    if blend == "feather":
        out = np.zeros((height, width, 4), np.uint8)
        strip = max(1, 2**18 // width)  # rows per strip: temporaries stay at a few MB whatever the region
        for top in range(0, height, strip):  # in strips, so the division needs no region-sized temporaries
            rows = slice(top, top + strip)
            strip_weight = weight_sum[rows]
            covered = strip_weight > 1e-6
            out[rows, :, :3] = np.clip(total[rows] / np.maximum(strip_weight, 1e-6)[..., None] + 0.5, 0, 255).astype(np.uint8)
            out[rows, :, 3] = np.where(covered, 255, 0).astype(np.uint8)
            out[rows, :, :3][~covered] = 0
    elif blend == "multiband":
        out = np.zeros((height, width, 4), np.uint8)
        if fed:  # a tile no frame reaches stays transparent (OpenCV's blender needs at least one image)
            result, mask = blender.blend(None, None)
            out[..., :3] = np.clip(result, 0, 255).astype(np.uint8)
            out[..., 3] = np.where(mask > 0, 255, 0).astype(np.uint8)
    return out


def _feed(blender, image: np.ndarray, region_from_frame: np.ndarray, box: tuple[int, int, int, int], owned: np.ndarray,
          gain: np.ndarray | None) -> int:
    """Feed the part of a frame that matters to the multiband ``blender``: the bounding box of the pixels it owns
    (``owned``, (h, w) bool over its region ``box``) widened by :data:`FEED_MARGIN`, warped from ``image``
    (H, W, 3) BGR uint8 by ``region_from_frame`` (3, 3) and scaled by its ``gain`` (:mod:`.gains`). Returns 1 if
    fed, 0 when it owns nothing. (Feeding a slanted strip in pieces was tried: the margins overlap, so it fed more
    pixels, and the blender's int16 sums round once per piece.)"""
    owned_u8 = owned.view(np.uint8)
    left, top, width, height = cv2.boundingRect(owned_u8)
    if width == 0:
        return 0
    bx0, by0, bx1, by1 = box
    # Box-relative corners of what is fed.
    fx0, fy0 = max(0, left - FEED_MARGIN), max(0, top - FEED_MARGIN)
    fx1, fy1 = min(bx1 - bx0, left + width + FEED_MARGIN), min(by1 - by0, top + height + FEED_MARGIN)
    fed_box = (bx0 + fx0, by0 + fy0, bx0 + fx1, by0 + fy1)
    scaled = _scaled(_warp(image, region_from_frame, fed_box), gain, box, (fx0, fy0, fx1, fy1))
    blender.feed(scaled, owned_u8[fy0:fy1, fx0:fx1] * np.uint8(255), fed_box[:2])
    return 1


def _scaled(warped: np.ndarray, gain: np.ndarray | None, box: tuple[int, int, int, int], cut: tuple[int, int, int, int]) -> np.ndarray:
    """(h, w, 3) uint8 warped pixels times their ``gain`` as the blender takes them: int16 in 0-255, truncated as
    :func:`.gains.apply_gain` followed by a cast truncates. A gain map is stretched over the frame's whole canvas
    ``box`` (x0, y0, x1, y1), then ``cut`` to the box-relative (x0, y0, x1, y1) of ``warped``."""
    if gain is None:
        return warped.astype(np.int16)
    if gain.ndim == 1:  # cv2.transform rounds and saturates at 255: rounding x - TRUNCATE truncates x
        return cv2.transform(warped, np.hstack([np.diag(gain), np.full((3, 1), -TRUNCATE)])).astype(np.int16)
    x0, y0, x1, y1 = cut
    gain_map = cv2.resize(gain.astype(np.float32), (box[2] - box[0], box[3] - box[1]), interpolation=cv2.INTER_LINEAR)[y0:y1, x0:x1]
    return np.clip(warped * gain_map, 0, 255).astype(np.int16)


PREVIEW_SIDE = 1200  # longest side of a mosaic's preview, pixels


class PreviewDrawer:
    """A small copy of a mosaic drawn from its tiles as they are blended (:func:`composite_tiles`), so that a
    mosaic streamed to a file gets its preview without being held whole."""

    def __init__(self, canvas_size: tuple[int, int], max_side: int = PREVIEW_SIDE) -> None:
        width, height = canvas_size
        self.scale = min(1.0, max_side / max(width, height))
        self.small = np.zeros((max(1, round(height * self.scale)), max(1, round(width * self.scale)), 4), np.uint8)

    def add(self, box: tuple[int, int, int, int], tile: np.ndarray) -> None:
        """Draw the canvas tile at ``box`` (x0, y0, x1, y1); tiles that share an edge share it here too."""
        x0, y0, x1, y1 = (round(v * self.scale) for v in box)
        if x1 > x0 and y1 > y0:
            self.small[y0:y1, x0:x1] = cv2.resize(tile, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)

    def image(self, background: int = 40) -> np.ndarray:
        """(h, w, 3) BGR uint8 on a dark background where nothing is drawn."""
        alpha = self.small[..., 3:4].astype(np.float32) / 255.0
        return (self.small[..., :3] * alpha + background * (1 - alpha) + 0.5).astype(np.uint8)


def preview(mosaic_bgra: np.ndarray, max_side: int = PREVIEW_SIDE, background: int = 40) -> np.ndarray:
    """(h, w, 3) BGR uint8 small copy of the mosaic on a dark background, for a quick look."""
    height, width = mosaic_bgra.shape[:2]
    drawer = PreviewDrawer((width, height), max_side)
    drawer.add((0, 0, width, height), mosaic_bgra)
    return drawer.image(background)
