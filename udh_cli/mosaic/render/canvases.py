"""Drawing every part: its canvas planned (and a too-big one refused) before any pixel, then its frames
composited tile by tile with exposure gains and seams, and its image and preview staged."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.images import write_image
from udh_cli.mosaic.georef.geotiff import streams_to_file, write_tiled_tiff
from udh_cli.mosaic.georef.place import PartOnCanvas
from udh_cli.mosaic.inputs.frames import FrameSet
from udh_cli.mosaic.outputs.files import MosaicFiles, RunFiles
from udh_cli.mosaic.outputs.png_stream import StreamedPng, bands
from udh_cli.mosaic.outputs.staging import StagedFiles
from udh_cli.mosaic.render import composite as compositing
from udh_cli.mosaic.render.decoded import DecodedFrames
from udh_cli.mosaic.render.gains import exposure_gains, mean_gain
from udh_cli.mosaic.render.seams import find_seams
from udh_cli.mosaic.render.small import draw_small
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.solve.parts import Part

KEPT_IMAGES_BYTES = 512 * 2**20  # parts' images held for the georeferencing at most (kept_images)


@dataclass(frozen=True)
class Drawing:
    """How parts are drawn (:class:`~udh_cli.mosaic.config.MosaicConfig` holds these, and says why).

    Attributes:
        blend, exposure, seams: :data:`.composite.BLENDS`, :data:`.gains.EXPOSURES`, :data:`.seams.SEAM_FINDERS`.
        max_frame_scale: frames the solve draws more than this many times larger or smaller are left out.
        max_size: longest side of a canvas, pixels (None: full resolution).
        max_canvas_bytes: a larger canvas is refused before any pixel is drawn.
        workers: local processes blending tiles.
        preview: also stage a small JPEG preview of each part.
    """

    blend: str
    exposure: str
    seams: str
    max_frame_scale: float
    max_size: int | None
    max_canvas_bytes: int
    workers: int
    preview: bool


@dataclass(frozen=True)
class PlannedPart:
    """A part that will be drawn: its solved part, its number among the drawn parts (from 1), the frames drawn
    (the part's frames but those the solve carried past the horizon), its canvas and its image file."""

    part: Part
    number: int
    frames: list[int]
    canvas: compositing.Canvas
    file: Path

    def mosaic_from_frame(self, i: int) -> np.ndarray:
        """(3, 3) frame ``i``'s pixels to the canvas's."""
        return self.canvas.mosaic_from_ref @ self.part.solved[i]


@dataclass(frozen=True)
class CanvasPlan:
    """Every part to draw, and each frame left out of its part's canvas with the reason (frame -> why)."""

    parts: list[PlannedPart]
    dropped: dict[int, str]


@dataclass(frozen=True)
class DrawnPart:
    """A part as written (staged): its plan, its preview (None without one), each frame's mean exposure gain
    per channel (B, G, R), and ``image``, the (H, W, 4) BGRA mosaic as written when the caller asked to keep it
    (None otherwise, and for a streamed TIFF)."""

    plan: PlannedPart
    preview: Path | None
    gains: dict[int, list[float]]
    image: np.ndarray | None = field(default=None, repr=False, compare=False)


def kept_images(plan: "CanvasPlan", wanted: bool, budget_bytes: int = KEPT_IMAGES_BYTES) -> set[int]:
    """The numbers of the parts whose assembled image :func:`composite_part` keeps for the georeferencing after it
    (``wanted``), in plan order while their BGRA bytes together stay within ``budget_bytes``; a streamed TIFF is
    never held whole. Why: the north-up GeoTIFF is drawn from the image in hand instead of decoding the staged
    file again; the budget bounds what a split flight holds at once."""
    kept, total = set(), 0
    for part in plan.parts if wanted else []:
        width, height = part.canvas.size
        if streams_to_file(part.file) or total + 4 * width * height > budget_bytes:
            continue
        kept.add(part.number)
        total += 4 * width * height
    return kept


def plan_canvases(frameset: FrameSet, parts: list[Part], files: RunFiles, settings: Drawing) -> CanvasPlan:
    """Every canvas is planned (and a too-big one refused) before any pixel is written."""
    sizes = [f.size for f in frameset.frames]
    dropped: dict[int, str] = {}
    kept = []
    for part in parts:
        # A long chain can carry a frame past the horizon of the reference's plane: report it, do not draw it.
        frames = []
        for i in part.frames:
            if geometry.is_valid_homography(part.solved[i], *sizes[i], max_scale=settings.max_frame_scale):
                frames.append(i)
            else:
                dropped[i] = (f"its homography to the reference frame {frameset.frames[part.reference].name} is degenerate "
                              f"(folded, past the horizon or scaled over {settings.max_frame_scale:g}x; see --max-frame-scale)")
        kept.append((part, frames))
    multi = [(part, frames) for part, frames in kept if len(frames) > 1]
    if not multi:
        raise UdhError("no pair of frames could be matched, so nothing can be mosaicked; try --fallback sift or a larger --work-size")
    planned = []
    for number, ((part, frames), path) in enumerate(zip(multi, files.parts(len(multi))), start=1):
        canvas = compositing.plan_canvas({i: part.solved[i] for i in frames}, sizes, settings.blend, settings.max_size,
                                         settings.max_canvas_bytes, assembled=not streams_to_file(path), one_tile=frameset.is_video)
        planned.append(PlannedPart(part, number, frames, canvas, path))
    return CanvasPlan(planned, dropped)


def composite_part(frameset: FrameSet, plan: PlannedPart, settings: Drawing, reporter: Reporter, staged: StagedFiles,
                   keep_image: bool = False) -> DrawnPart:
    """Composite one part and write its image and preview under the temporary names of ``staged``; with
    ``keep_image`` (and an image assembled whole) the :class:`DrawnPart` holds it."""
    to_mosaic = {i: plan.mosaic_from_frame(i) for i in plan.frames}
    suffix = "" if plan.number == 1 else f" part {plan.number}"
    gains, seams = None, None
    # The frames decoded while reading, then the small copies' decodes, kept for the tiles.
    decoded = DecodedFrames.taken_from(frameset, plan.frames)
    want_seams = settings.seams != "central" and settings.blend != "feather"
    if settings.exposure != "none" or want_seams:
        small = draw_small(frameset, to_mosaic, plan.canvas.scale, reporter, f"small copies{suffix}", decoded)
        with reporter.stage("colour and seams", 1, f"colour and seams{suffix}") as advance:
            gains = exposure_gains(settings.exposure, small)
            seams = find_seams(settings.seams, small, settings.workers) if want_seams else None
            advance(1)
    tiles = compositing.composite_tiles(frameset, to_mosaic, plan.canvas.size, settings.blend, reporter, f"compositing{suffix}", gains, seams,
                                        workers=settings.workers, decoded=decoded)
    drawer = compositing.PreviewDrawer(plan.canvas.size)
    kept = None
    file_type = plan.file.suffix.lower()
    if streams_to_file(plan.file):  # blended and written tile by tile: the map's area costs no memory
        write_tiled_tiff(staged.path_for(plan.file), plan.canvas.size, _drawn(tiles, drawer))
    elif file_type == ".png":  # each band compressed beside the next tiles' blending (png_stream)
        kept = _write_png(staged.path_for(plan.file), plan.canvas.size, _drawn(tiles, drawer), reporter, settings.workers, keep_image)
    else:
        mosaic = compositing.assemble(_drawn(tiles, drawer), plan.canvas.size)
        with reporter.stage("writing", 1) as advance:
            if file_type in (".jpg", ".jpeg"):
                reporter.warn(f"{plan.file.name}: JPEG has no alpha channel; uncovered areas are black (use .png or .tif to keep the mask)")
                write_image(staged.path_for(plan.file), mosaic[..., :3])
            else:
                write_image(staged.path_for(plan.file), mosaic)
            advance(1)
        kept = mosaic if keep_image else None
        del mosaic
    preview = MosaicFiles(plan.file).preview if settings.preview else None
    if preview is not None:
        write_image(staged.path_for(preview), drawer.image())
    return DrawnPart(plan, preview, {i: mean_gain(gains[i]) if gains is not None else [1.0, 1.0, 1.0] for i in plan.frames}, kept)


def _write_png(path: Path, size: tuple[int, int], tiles, reporter: Reporter, threads: int, keep_image: bool) -> np.ndarray | None:
    """Stream row-major ``tiles`` into a PNG at ``path``; with ``keep_image`` returns the (H, W, 4) BGRA canvas
    assembled from them too. The "writing" stage times only what is left to compress after the last tile."""
    kept = np.zeros((size[1], size[0], 4), np.uint8) if keep_image else None
    png = StreamedPng(path, size, 4, threads)
    try:
        for top, band in bands(tiles, size):
            png.add_rows(top, band)
            if kept is not None:
                kept[top : top + band.shape[0]] = band
    except BaseException:
        png.abandon()
        raise
    with reporter.stage("writing", 1) as advance:
        png.close()
        advance(1)
    return kept


def _drawn(tiles, drawer: "compositing.PreviewDrawer"):
    """``tiles`` passed on, each also drawn into the preview."""
    for box, tile in tiles:
        drawer.add(box, tile)
        yield box, tile


def on_canvas(plan: CanvasPlan) -> list[PartOnCanvas]:
    """The parts drawn, each with its frames' ``mosaic_from_frame`` (h33 = 1), as the sidecar and the map
    placement read them."""
    drawn = []
    for part in plan.parts:
        mosaic_from_frame = {}
        for i in part.frames:
            matrix = part.mosaic_from_frame(i)
            mosaic_from_frame[i] = matrix / matrix[2, 2]
        drawn.append(PartOnCanvas(part.number, part.file, list(part.frames), mosaic_from_frame))
    return drawn


def warn_about_earlier_output(files: RunFiles, plan: CanvasPlan, reporter: Reporter) -> None:
    """A split run does not write the output itself: one there now is an earlier run's and is left alone."""
    if len(plan.parts) > 1 and files.output.is_file():
        reporter.warn(f"{files.output.name} is left from an earlier run: this run is split into parts, which are written as {plan.parts[0].file.name}, ...")
