"""Ground-control points in OpenDroneMap's ``gcp_list.txt`` format, and how well a mosaic fits them.

The format: the first line is the CRS (a PROJ string such as ``+proj=utm +zone=11 +datum=WGS84``, or
``EPSG:32611``; ``WGS84`` / ``+proj=longlat`` for longitude-latitude degrees), then one observation per line,
``x y z px py image [name]``: the point's map coordinates, and the pixel where it is seen in one frame. A point
seen in several frames has several lines with the same name.

Each point's observations go through the solved ``mosaic_from_frame`` into mosaic pixels; the spread of one
point's observations measures the mosaic's own consistency (the same target seen from two passes should land
on one pixel). The map placement is fitted to the points, and every point is checked by leaving it out
(a checkpoint): a point the others contradict, such as a label on the wrong target, is reported and left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.files import read_side_file
from udh_cli.mosaic.georef.gps import MIN_GPS_FRAMES, fit_similarity

MIN_GCPS = MIN_GPS_FRAMES  # a similarity has 4 unknowns: three points leave one check
OBSERVATION_SPREAD_PX = 50.0  # one point's observations farther apart in the mosaic are not one target
SAME_PIXEL_PX = 3.0  # two points marked this close in one image are one target given two labels
INCONSISTENT_M = 1.0  # a checkpoint error above this and OUTLIER_FACTOR x the median marks a contradicting point
OUTLIER_FACTOR = 4.0
MAX_MAP_COORDINATE_M = 1e8  # projected coordinates stay within the Earth's circumference, 4e7 m
MAX_ELEVATION_M = 1e5  # far above any terrain, in metres or in feet
SAME_SPOT_M = 0.01  # distinct points closer than this all over cannot place or scale a map


@dataclass(frozen=True)
class Observation:
    x: float
    y: float
    z: float
    px: float
    py: float
    image: str
    name: str
    line: int


@dataclass
class GcpFile:
    """A parsed ``gcp_list.txt``: its CRS (EPSG code of a projected CRS) and its observations."""

    epsg: int
    observations: list[Observation] = field(default_factory=list)


def read_gcp_file(path: str | Path) -> GcpFile:
    """Parse and check a GCP file; :class:`UdhError` names the line and what is wrong with it."""
    path = Path(path)
    # A byte-order mark (Windows editors) is not part of the CRS line.
    lines = read_side_file(path, "--gcp").decode("utf-8-sig", errors="replace").splitlines()
    lines = [line for line in lines if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise UdhError(f"{path}: empty GCP file; the first line is the CRS, then one 'x y z px py image [name]' per line")
    epsg, geographic = _crs(lines[0].strip(), path)
    observations = []
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split()
        if len(fields) < 6:
            raise UdhError(f"{path}, line {number}: expected 'x y z px py image [name]', got {len(fields)} fields")
        try:
            x, y, z, px, py = (float(v) for v in fields[:5])
        except ValueError:
            raise UdhError(f"{path}, line {number}: x, y, z, px and py must be numbers") from None
        if not all(math.isfinite(v) for v in (x, y, z, px, py)):
            raise UdhError(f"{path}, line {number}: a coordinate is not finite")
        if geographic and not (-180.0 <= x <= 180.0 and -90.0 <= y <= 90.0):
            raise UdhError(f"{path}, line {number}: {x:g} {y:g} are not longitude and latitude degrees, as the CRS line says; "
                           f"give the CRS the numbers are in (e.g. EPSG:32611 for UTM zone 11N)")
        if max(abs(x), abs(y)) > MAX_MAP_COORDINATE_M or abs(z) > MAX_ELEVATION_M:
            raise UdhError(f"{path}, line {number}: {x:g} {y:g} {z:g} is no place on Earth in a projected CRS; check the numbers")
        name = fields[6] if len(fields) > 6 else f"line{number}"
        observations.append(Observation(x, y, z, px, py, fields[5], name, number))
    if not observations:
        raise UdhError(f"{path}: no ground-control points after the CRS line; add one 'x y z px py image [name]' per line")
    if geographic:  # longitude, latitude degrees: to the UTM zone of their centre
        from udh_cli.mosaic.georef.gps import utm_transformer, utm_epsg

        lon, lat = np.median([o.x for o in observations]), np.median([o.y for o in observations])
        epsg = utm_epsg(float(lat), float(lon))
        eastings, northings = utm_transformer(epsg).transform([o.x for o in observations], [o.y for o in observations])
        observations = [Observation(e, n, o.z, o.px, o.py, o.image, o.name, o.line) for o, e, n in zip(observations, eastings, northings)]
    positions = np.array(list({o.name: (o.x, o.y) for o in observations}.values()))
    if len(positions) > 1 and np.ptp(positions, axis=0).max() < SAME_SPOT_M:  # no scale or heading can come from one spot
        raise UdhError(f"{path}: all {len(positions)} ground-control points lie at one spot on the map; check their coordinates")
    return GcpFile(epsg, observations)


def _crs(text: str, path: Path) -> tuple[int, bool]:
    """(EPSG code, whether the coordinates are longitude-latitude degrees) of the header line."""
    try:
        from pyproj import CRS
        from pyproj.exceptions import CRSError
    except ImportError:
        raise UdhError("ground-control points need pyproj: pip install pyproj (from the udh checkout: pip install '.[geo]')") from None
    try:
        crs = CRS.from_user_input("EPSG:4326" if text.upper() in ("WGS84", "WGS 84") else text)
    except CRSError:
        raise UdhError(f"{path}, line 1: unknown CRS '{text[:60]}'; give a PROJ string (+proj=utm +zone=11 +datum=WGS84) or EPSG:code") from None
    if crs.is_geographic:
        return 4326, True
    epsg = crs.to_epsg(min_confidence=70)
    if epsg is None or not crs.is_projected:
        raise UdhError(f"{path}, line 1: the CRS '{text[:60]}' has no EPSG code udh can write; use a UTM zone (EPSG:326zz or 327zz)")
    return int(epsg), False


@dataclass(frozen=True)
class GcpFit:
    """The mosaic placed on the map by its ground-control points.

    Attributes:
        epsg: the CRS; map_from_mosaic: (3, 3) similarity, mosaic pixels to map metres.
        points: per point name: ``observations`` (frames seen in), ``spread_px`` (largest distance between its
            observations in the mosaic), ``checkpoint_m`` (error when left out of the fit), ``used``,
            ``mosaic_px`` (where it lies in the mosaic, pixels) and ``map_m`` (its map position, metres).
        checkpoint_rms_m: RMS of the used points' checkpoint errors (each point left out in turn).
        residual_rms_m: RMS residual of the used points in the fit with all of them.
        skipped: observations that could not be used, with why (frame not placed, pixel outside the frame).
    """

    epsg: int
    map_from_mosaic: np.ndarray
    points: dict[str, dict]
    checkpoint_rms_m: float
    residual_rms_m: float
    skipped: list[str]

    def to_json(self) -> dict:
        return {"source": "gcp", "crs": f"EPSG:{self.epsg}", "map_from_mosaic": self.map_from_mosaic.tolist(),
                "gcp_checkpoint_rms_m": self.checkpoint_rms_m, "gcp_residual_rms_m": self.residual_rms_m,
                "gcps": self.points, "gcp_skipped": self.skipped,
                "pixel_size_m": float(math.hypot(self.map_from_mosaic[0, 0], self.map_from_mosaic[1, 0]))}


def fit_gcps(gcps: GcpFile, frames: dict[str, tuple[tuple[int, int], np.ndarray | None]], image_width: int | None = None) -> GcpFit:
    """Place a mosaic part by ground-control points.

    Args:
        gcps: the parsed file.
        frames: frame file name -> ((width, height) at full resolution, ``mosaic_from_frame`` or None when the
            frame is not in this part).
        image_width: the width of the images the file's pixels refer to, when they were measured on other
            copies of the frames (the originals before downscaling); None: the frames themselves.

    Raises :class:`UdhError` when fewer than :data:`MIN_GCPS` points can be used.
    """
    skipped: list[str] = []
    seen: dict[str, list[np.ndarray]] = {}
    where: dict[str, np.ndarray] = {}
    for o in _contradicting_labels(gcps.observations, skipped):
        if o.image not in frames:
            skipped.append(f"{o.name} (line {o.line}): image {o.image} is not among the frames")
            continue
        (width, height), mosaic_from_frame = frames[o.image]
        px, py = _frame_pixel(o, width, image_width)
        if not (-0.5 <= px <= width - 0.5 and -0.5 <= py <= height - 0.5):
            skipped.append(f"{o.name} (line {o.line}): pixel ({o.px:g}, {o.py:g}) is outside {o.image}'s {width}x{height} pixels"
                           + ("" if image_width else "; if the file refers to the original images, give their width (--gcp-image-width)"))
            continue
        if mosaic_from_frame is None:
            skipped.append(f"{o.name} (line {o.line}): {o.image} is not placed in this mosaic")
            continue
        seen.setdefault(o.name, []).append(geometry.transform_points(mosaic_from_frame, np.array([[px, py]]))[0])
        where[o.name] = np.array([o.x, o.y])
    names = sorted(seen)
    if len(names) < MIN_GCPS:
        raise UdhError(f"only {len(names)} ground-control point(s) usable in this mosaic (need {MIN_GCPS})"
                       + (f": {skipped[0]}" if skipped else ""))
    for n in names:  # with three or more observations, one far from the others' median is a mislabel
        if len(seen[n]) >= 3:
            median = np.median(seen[n], axis=0)
            near = [p for p in seen[n] if np.linalg.norm(p - median) <= OBSERVATION_SPREAD_PX]
            if len(near) < len(seen[n]):
                skipped.append(f"{n}: {len(seen[n]) - len(near)} of its {len(seen[n])} observations land over "
                               f"{OBSERVATION_SPREAD_PX:g} px from the others in the mosaic (a mislabelled target, or the mosaic "
                               f"disagreeing with itself there): left out")
                seen[n] = near or seen[n]
    mosaic = np.array([np.median(seen[n], axis=0) for n in names])
    ground = np.array([where[n] for n in names])
    spread = {n: float(max((np.linalg.norm(p - q) for p in seen[n] for q in seen[n]), default=0.0)) for n in names}
    used = np.ones(len(names), bool)
    checkpoint = _leave_one_out(mosaic, ground, used)
    for _ in range(len(names)):  # drop the worst contradicting point, one at a time, while one stands out
        candidates = np.where(used)[0]
        if len(candidates) <= MIN_GCPS:
            break
        worst = candidates[np.argmax(checkpoint[candidates])]
        others = np.median(np.delete(checkpoint[candidates], np.argmax(checkpoint[candidates])))
        if checkpoint[worst] <= max(INCONSISTENT_M, OUTLIER_FACTOR * others):
            break
        used[worst] = False
        checkpoint = _leave_one_out(mosaic, ground, used)
    fit = fit_similarity(mosaic[used], ground[used])
    residuals = np.linalg.norm(geometry.transform_points(fit, mosaic) - ground, axis=1)
    points = {n: {"observations": len(seen[n]), "spread_px": spread[n], "checkpoint_m": float(checkpoint[k]),
                  "residual_m": float(residuals[k]), "used": bool(used[k]),
                  "mosaic_px": mosaic[k].tolist(), "map_m": ground[k].tolist()} for k, n in enumerate(names)}
    return GcpFit(gcps.epsg, fit, points, float(np.sqrt(np.mean(checkpoint[used] ** 2))),
                  float(np.sqrt(np.mean(residuals[used] ** 2))), skipped)


def gcp_anchors(gcps: GcpFile, frames: dict[str, tuple[int, tuple[int, int]]], sigma_m: float, image_width: int | None = None,
                leave_out: str | None = None):
    """The observations as anchors of the global solve (:class:`~udh_cli.mosaic.georef.anchors.Anchors`), in the file's CRS.

    ``frames``: file name -> (frame index, (width, height) at full resolution); ``image_width`` as in
    :func:`fit_gcps`. Marks that contradict each other (:func:`_contradicting_labels`), images that are not
    frames and pixels outside their frame are left out, as the fit leaves them out. ``leave_out``: a point's
    name whose observations are left out too (to check it honestly). None when no observation is usable.
    """
    from udh_cli.mosaic.georef.anchors import Anchors

    rows = []
    for o in _contradicting_labels(gcps.observations, []):
        if o.image not in frames or o.name == leave_out:
            continue
        index, (width, height) = frames[o.image]
        px, py = _frame_pixel(o, width, image_width)
        if -0.5 <= px <= width - 0.5 and -0.5 <= py <= height - 0.5:
            rows.append((index, px, py, o.x, o.y))
    if not rows:
        return None
    table = np.array(rows, np.float64)
    return Anchors(table[:, 0].astype(int), table[:, 1:3], table[:, 3:5], np.full(len(rows), float(sigma_m)))


def _file_to_frame(width: int, image_width: int | None) -> float:
    """Frame pixels per pixel of the file (``image_width``: the width its pixels refer to; None: the frame's)."""
    return 1.0 if image_width is None else width / image_width


def _frame_pixel(o: Observation, width: int, image_width: int | None) -> tuple[float, float]:
    """An observation's pixel in the full-resolution frame of ``width``."""
    scale = _file_to_frame(width, image_width)
    return o.px * scale, o.py * scale


def _contradicting_labels(observations: list[Observation], skipped: list[str]) -> list[Observation]:
    """The observations less those where two differently named points are marked on the same pixel of one
    image but lie apart on the ground: one target cannot carry two positions, so both marks are left out."""
    bad: set[int] = set()
    for i, a in enumerate(observations):
        for j in range(i + 1, len(observations)):
            b = observations[j]
            if (a.image == b.image and a.name != b.name and math.hypot(a.px - b.px, a.py - b.py) <= SAME_PIXEL_PX
                    and math.hypot(a.x - b.x, a.y - b.y) > INCONSISTENT_M):
                bad.update((i, j))
                skipped.append(f"{a.name} and {b.name} are marked on the same pixel of {a.image} but lie "
                               f"{math.hypot(a.x - b.x, a.y - b.y):.1f} m apart: both marks left out (lines {a.line}, {b.line})")
    return [o for k, o in enumerate(observations) if k not in bad]


def _leave_one_out(mosaic: np.ndarray, ground: np.ndarray, used: np.ndarray) -> np.ndarray:
    """For every point: its error when the fit uses the other ``used`` points (a checkpoint), metres."""
    errors = np.empty(len(mosaic))
    for k in range(len(mosaic)):
        others = used.copy()
        others[k] = False
        fit = fit_similarity(mosaic[others], ground[others])
        errors[k] = np.linalg.norm(geometry.transform_points(fit, mosaic[k : k + 1])[0] - ground[k])
    return errors


def undistorted_observations(gcps: GcpFile, lens, sizes: dict[str, tuple[int, int]], image_width: int | None = None) -> GcpFile:
    """The file with every observation's pixel moved where the camera model (:class:`.lens.Lens`) undistorts it,
    in the same units as the file's (``image_width``: see :func:`fit_gcps`); observations of frames not in
    ``sizes`` (file name -> full (width, height)) are kept as they are, and reported later."""
    moved = []
    for o in gcps.observations:
        if o.image not in sizes:
            moved.append(o)
            continue
        width, height = sizes[o.image]
        scale = _file_to_frame(width, image_width)
        px, py = lens.undistort_points(np.array([_frame_pixel(o, width, image_width)]), (width, height))[0] / scale
        moved.append(replace(o, px=float(px), py=float(py)))
    return GcpFile(gcps.epsg, moved)
