"""Georeferencing a mosaic from its frames' GPS: a world file and a projection file that GIS tools open.

Each placed frame with EXIF GPS gives one correspondence: its centre in the mosaic's pixels and its
position in the local UTM zone (pyproj). A similarity (scale, rotation, shift, with the mosaic's y axis
pointing down and northing up) is fitted robustly to them, and written as an ESRI world file beside the
mosaic (``.pgw`` for PNG, ``.tfw`` for TIFF, ``.jgw`` for JPEG) plus a ``.prj`` with the CRS. GDAL, QGIS and
ArcGIS then place the mosaic on the map, rotation included; the pixels are not resampled.

The GPS of a small drone is good to a few metres, so a map placed this way is good to a few metres too; the
residual of each frame is reported, and a frame whose GPS disagrees with the others by far is left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError

MIN_GPS_FRAMES = 3  # a similarity has 4 unknowns; three frames leave one check
MIN_GPS_SPREAD_M = 1.0  # fixes all closer than this are one fix repeated: they give the map no scale
OUTLIER_FACTOR = 4.0  # a frame whose GPS residual exceeds this many times the median (and 5 m) is a bad fix
OUTLIER_FLOOR_M = 5.0


@dataclass(frozen=True)
class Georeference:
    """Where a mosaic lies on the map.

    Attributes:
        epsg: the projected CRS (WGS 84 / UTM zone), e.g. 32615.
        map_from_mosaic: (3, 3) affine map from mosaic pixel coordinates (pixel centres at integers, y down)
            to easting and northing in metres.
        frames_used: indices of the frames whose GPS the fit used; frames_rejected: those left out as bad fixes.
        residual_rms_m: RMS distance between the used frames' GPS positions and where the fit puts their centres.
        pixel_size_m: ground size of one mosaic pixel, metres.
        north_deg: the bearing of the mosaic's up direction, degrees clockwise from grid north.
    """

    epsg: int
    map_from_mosaic: np.ndarray
    frames_used: tuple[int, ...]
    frames_rejected: tuple[int, ...]
    residual_rms_m: float
    pixel_size_m: float
    north_deg: float

    def to_json(self) -> dict:
        return {"source": "gps", "crs": f"EPSG:{self.epsg}", "map_from_mosaic": self.map_from_mosaic.tolist(), "gps_frames": len(self.frames_used),
                "gps_checked": len(self.frames_used) >= MIN_GPS_FRAMES,
                "gps_frames_rejected": list(self.frames_rejected), "gps_residual_rms_m": self.residual_rms_m,
                "pixel_size_m": self.pixel_size_m, "north_deg": self.north_deg}


def utm_epsg(latitude: float, longitude: float) -> int:
    """The EPSG code of the WGS 84 / UTM zone holding a point (326zz north, 327zz south)."""
    zone = min(60, max(1, int(math.floor((longitude + 180.0) / 6.0)) + 1))
    return (32600 if latitude >= 0 else 32700) + zone


def utm_transformer(epsg: int):
    """pyproj's WGS 84 longitude/latitude -> ``epsg`` transformer (``always_xy``); a clear error without pyproj."""
    try:
        from pyproj import Transformer
    except ImportError:
        raise UdhError("georeferencing needs pyproj: pip install pyproj (or, from the udh checkout, pip install '.[geo]')") from None
    return Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)


def to_utm(latitudes: np.ndarray, longitudes: np.ndarray) -> tuple[int, np.ndarray]:
    """WGS 84 degrees -> ``(epsg, (N, 2) easting and northing metres)`` in the UTM zone of the median position."""
    epsg = utm_epsg(float(np.median(latitudes)), float(np.median(longitudes)))
    eastings, northings = utm_transformer(epsg).transform(longitudes, latitudes)
    return epsg, np.column_stack([eastings, northings])


def fit_similarity(mosaic_points: np.ndarray, map_points: np.ndarray) -> np.ndarray:
    """Least-squares similarity from mosaic pixels (N, 2; y down) to map metres (N, 2; y up): (3, 3) affine.

    The y flip makes it a reflection of the image plane, which a similarity of the flipped coordinates
    models exactly: ``map = s R (x, -y) + t`` (Umeyama's closed form, no iteration).
    """
    flipped = mosaic_points * [1.0, -1.0]
    mean_src, mean_dst = flipped.mean(0), map_points.mean(0)
    src, dst = flipped - mean_src, map_points - mean_dst
    covariance = dst.T @ src / len(src)
    u, singular, vt = np.linalg.svd(covariance)
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ d @ vt
    variance = (src**2).sum() / len(src)
    scale = float(np.trace(np.diag(singular) @ d) / variance) if variance > 0 else 1.0
    linear = scale * rotation @ np.diag([1.0, -1.0])
    shift = mean_dst - linear @ (mean_src * [1.0, -1.0])
    out = np.eye(3)
    out[:2, :2], out[:2, 2] = linear, shift
    return out


def georeference_part(frames: Sequence[tuple[int, tuple[int, int], np.ndarray, float, float]],
                      min_frames: int = MIN_GPS_FRAMES) -> Georeference | None:
    """Fit a part's georeference from ``(frame index, (width, height), mosaic_from_frame, latitude, longitude)``
    of its placed frames that have GPS; None with fewer than ``min_frames`` (two fix a similarity exactly,
    with nothing left to check it), or when every fix is at one spot (a receiver repeating one fix: no scale)."""
    if len(frames) < max(2, min_frames):
        return None
    latitudes, longitudes = np.array([f[3] for f in frames]), np.array([f[4] for f in frames])
    epsg, map_points = to_utm(latitudes, longitudes)
    if np.ptp(map_points, axis=0).max() < MIN_GPS_SPREAD_M:
        return None
    centres = np.array([geometry.transform_points(h, np.array([[(w - 1) / 2, (hgt - 1) / 2]]))[0] for _, (w, hgt), h, _, _ in frames])
    used = np.ones(len(frames), bool)
    least = max(2, min_frames)
    for _ in range(3 if len(frames) >= MIN_GPS_FRAMES else 0):  # refit without bad fixes (a GPS jump), a few rounds at most
        if used.sum() < least:
            return None
        fit = fit_similarity(centres[used], map_points[used])
        residuals = np.linalg.norm(geometry.transform_points(fit, centres) - map_points, axis=1)
        limit = max(OUTLIER_FLOOR_M, OUTLIER_FACTOR * float(np.median(residuals[used])))
        keep = residuals <= limit
        if np.array_equal(keep, used):
            break
        used = keep
    if used.sum() < least:
        return None
    fit = fit_similarity(centres[used], map_points[used])
    residuals = np.linalg.norm(geometry.transform_points(fit, centres) - map_points, axis=1)
    a, b = fit[0, 0], fit[1, 0]
    return Georeference(
        epsg=epsg, map_from_mosaic=fit, frames_used=tuple(int(f[0]) for f, u in zip(frames, used) if u),
        frames_rejected=tuple(int(f[0]) for f, u in zip(frames, used) if not u),
        residual_rms_m=float(np.sqrt(np.mean(residuals[used] ** 2))), pixel_size_m=float(math.hypot(a, b)),
        # The mosaic's "up" (-y) direction, in degrees clockwise from north: what a viewer must turn.
        north_deg=float(math.degrees(math.atan2(-fit[0, 1], -fit[1, 1]))),
    )


def world_file_text(georeference: Georeference) -> str:
    """The six lines of an ESRI world file: A, D, B, E, C, F with X = A col + B row + C, Y = D col + E row + F,
    (col, row) the centre of a pixel, (C, F) that of the top-left one: udh's pixel convention exactly."""
    m = georeference.map_from_mosaic
    values = (m[0, 0], m[1, 0], m[0, 1], m[1, 1], m[0, 2], m[1, 2])
    return "".join(f"{v:.10f}\n" for v in values)


def projection_text(epsg: int) -> str:
    """The ``.prj`` content: the CRS as ESRI WKT, which every GIS reads beside a world file."""
    from pyproj import CRS

    return CRS.from_epsg(epsg).to_wkt("WKT1_ESRI") + "\n"
