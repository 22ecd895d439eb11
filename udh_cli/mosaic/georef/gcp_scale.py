"""Which pixels a ground-control file measures in: the frames' own, or those of the originals they were
downscaled from, and whether the fitted points agree.

A GCP file is usually made on the camera's originals (OpenDroneMap's GCP editor shows them), while the frames
given to udh are often smaller copies. The scale is read from two signs before any work: the observations
that fall outside their frame, and the original size the frames' EXIF keeps (``PixelXDimension``). Where the
signs do not settle it, the run refuses with a line naming ``--gcp-image-width``. After the fit, every point's
residual is reported, and a fit that another candidate scale beats by far stops the run before a map is written.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

from udh_cli.errors import UdhError
from udh_cli.mosaic.georef.gcp import INCONSISTENT_M, MIN_GCPS, GcpFile, GcpFit

ASPECT_TOLERANCE = 0.01  # an EXIF size of another aspect than the frame's is not its original
# All observations inside the frames' box, though they were measured on originals this much larger, would
# happen by chance with this probability at most: below it, the file is taken to be in the frames' pixels.
CHANCE = 0.01
WORSE_FACTOR = 2.0  # a scale whose checkpoint RMS is this many times another's (and over INCONSISTENT_M) is wrong


@dataclass(frozen=True)
class GcpScale:
    """The width the GCP file's pixels refer to, and why.

    Attributes:
        image_width: pixels across the images the file was measured on; None: the frames' own.
        reason: one line for the log and the sidecar.
    """

    image_width: int | None
    reason: str


def original_widths(frames: Sequence) -> set[int]:
    """The original widths (pixels) that the frames' EXIF records where it differs from the frame's own size
    with the same aspect (a downscaled copy), read across as the frame is (EXIF orientation applied)."""
    widths = set()
    for frame in frames:
        meta, (width, height) = frame.metadata, frame.size
        if meta is None or not meta.original_width or not meta.original_height:
            continue
        for across, down in ((meta.original_width, meta.original_height), (meta.original_height, meta.original_width)):
            if across != width and abs(across / down - width / height) <= ASPECT_TOLERANCE * width / height:
                widths.add(int(across))
                break
    return widths


def _outside(gcps: GcpFile, sizes: dict[str, tuple[int, int]], image_width: int | None) -> int:
    """How many observations of the frames in ``sizes`` fall outside their frame at ``image_width``."""
    count = 0
    for o in gcps.observations:
        if o.image in sizes:
            width, height = sizes[o.image]
            scale = 1.0 if image_width is None else width / image_width
            count += not (-0.5 <= o.px * scale <= width - 0.5 and -0.5 <= o.py * scale <= height - 0.5)
    return count


def infer_gcp_scale(gcps: GcpFile, frames: Sequence, given: int | None, file: str) -> GcpScale:
    """The GCP file's pixel scale: ``given`` (``--gcp-image-width``) when set, else read from the frames
    (``frames``: :class:`~udh_cli.mosaic.inputs.frames.Frame` with ``name``, ``size``, ``metadata``).

    Raises :class:`UdhError`, naming ``--gcp-image-width``, when neither the frames' pixels nor one EXIF
    original width holds the observations, or when nothing tells which of the two the file is in.
    """
    if given is not None:
        return GcpScale(given, f"--gcp-image-width {given}")
    sizes = {f.name: f.size for f in frames}
    seen = [o for o in gcps.observations if o.image in sizes]
    outside_own = _outside(gcps, sizes, None)
    originals = original_widths([f for f in frames if f.name in {o.image for o in seen}])
    widths = sorted({sizes[o.image][0] for o in seen})
    if len(originals) > 1:
        if outside_own == 0:
            return GcpScale(None, "the frames' own pixels (every observation falls inside its frame)")
        raise UdhError(f"{file}: {outside_own} of {len(seen)} observations fall outside their frames, and the frames' EXIF gives "
                       f"originals of several widths ({', '.join(map(str, sorted(originals)))} px); give the width the file "
                       "was measured on with --gcp-image-width")
    if not originals:
        if outside_own == 0:
            return GcpScale(None, "the frames' own pixels (every observation falls inside its frame)")
        raise UdhError(f"{file}: {outside_own} of {len(seen)} observations fall outside their {widths[0]}-px frames, so the file "
                       "refers to larger originals; give their width with --gcp-image-width")
    original = originals.pop()
    outside_original = _outside(gcps, sizes, original)
    if outside_own > 0 and outside_original == 0:
        return GcpScale(original, f"the originals' {original} px (EXIF): {outside_own} of {len(seen)} observations fall outside "
                                  f"the {widths[0]}-px frames, none outside the originals")
    if outside_own == 0:
        share = min(size[0] / original for size in sizes.values()) ** 2
        if share ** len(seen) <= CHANCE:
            return GcpScale(None, f"the frames' own pixels: all {len(seen)} observations fall inside the frames, which would be "
                                  f"unlikely in the {original}-px originals (EXIF)")
        raise UdhError(f"{file}: its {len(seen)} observations fit both the {widths[0]}-px frames and the {original}-px originals "
                       f"their EXIF names; say which with --gcp-image-width {widths[0]} or --gcp-image-width {original}")
    raise UdhError(f"{file}: observations fall outside their frames both in the frames' pixels ({outside_own} of {len(seen)}) "
                   f"and in the {original}-px originals' ({outside_original}); give the width the file was measured on with "
                   "--gcp-image-width")


def check_gcp_fit(found: GcpFit, fit_at: Callable[[int | None], GcpFit], scale: GcpScale | int | None, frames: Sequence) -> None:
    """Refuse a fit whose residuals say the pixel scale is wrong: another candidate scale (the frames' own, an
    EXIF original width) places the points far better. ``fit_at(width)`` fits the same part at another width
    (:func:`.gcp.fit_gcps`); ``scale`` is the width used (a :class:`GcpScale`, a width or None)."""
    used_width = scale.image_width if isinstance(scale, GcpScale) else scale
    if found.checkpoint_rms_m <= INCONSISTENT_M:
        return
    for width in sorted({None, *original_widths(frames)} - {used_width}, key=lambda w: w or 0):
        try:
            other = fit_at(width)
        except UdhError:  # too few points at that scale: no evidence against the one used
            continue
        if sum(p["used"] for p in other.points.values()) <= MIN_GCPS:
            continue  # with only the minimum, a checkpoint is one point against two: no verdict
        if found.checkpoint_rms_m > WORSE_FACTOR * other.checkpoint_rms_m:
            named = "the frames' own width" if width is None else f"{width} px"
            option = f"--gcp-image-width {width}" if width is not None else f"--gcp-image-width {frames[0].size[0]}"
            raise UdhError(f"the ground-control points fit {found.checkpoint_rms_m:.2f} m RMS at their checkpoints with the pixel scale "
                           f"used, {other.checkpoint_rms_m:.2f} m at {named}: the file's pixel scale is wrong, so no map is written; "
                           f"run again with {option}")


def residual_lines(found: GcpFit) -> list[str]:
    """One line per point: its observations, its residual in the fit and its checkpoint error (left out)."""
    lines = []
    for name, point in sorted(found.points.items()):
        lines.append(f"  {name}: {point['observations']} observation(s), residual {point['residual_m']:.2f} m, checkpoint "
                     f"{point['checkpoint_m']:.2f} m" + ("" if point["used"] else " (left out of the fit)"))
    return lines
