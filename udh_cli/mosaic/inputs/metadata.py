"""What a frame's file says about how it was taken: capture time, GPS position, camera and DJI flight data.

EXIF is read with Pillow (header only, never the pixels). DJI writes its flight data (relative altitude,
flight and gimbal yaw) as XMP attributes in the ``drone-dji`` namespace; Pillow exposes XMP only as a raw
packet (its parser needs defusedxml, which udh does not install), so those few attributes are read from
the packet with a pattern, as ODM and exiftool's users commonly do.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

_GPS_IFD = 0x8825
_EXIF_IFD = 0x8769
_DATE_TIME_ORIGINAL = 0x9003
_DATE_TIME = 0x0132
_FOCAL_LENGTH = 0x920A
_FOCAL_35MM = 0xA405
_MAKE, _MODEL = 0x010F, 0x0110
_PIXEL_X, _PIXEL_Y = 0xA002, 0xA003  # the size the camera wrote; a downscaled copy often keeps the original's
_DJI = re.compile(rb'drone-dji:(RelativeAltitude|AbsoluteAltitude|FlightYawDegree|GimbalYawDegree|GimbalPitchDegree)\s*=\s*"([^"]{1,32})"')
_XMP_SCAN_BYTES = 256 * 1024  # DJI's XMP packet sits in the first APP1 segments of the JPEG


@dataclass(frozen=True)
class FrameMetadata:
    """Metadata of one frame; every field is None when the file does not say.

    Attributes:
        capture_time: ``"YYYY:MM:DD HH:MM:SS"`` (DateTimeOriginal, else DateTime).
        latitude, longitude: WGS84 degrees, north and east positive.
        altitude_m: GPS altitude, metres above sea level.
        relative_altitude_m: DJI's height above the take-off point, metres.
        flight_yaw_deg, gimbal_yaw_deg, gimbal_pitch_deg: DJI's aircraft and camera angles, degrees.
        focal_length_mm, focal_length_35mm: the lens, as EXIF gives it.
        camera: make and model (the make once: "Canon PowerShot", not "Canon Canon PowerShot").
        original_width, original_height: the image size EXIF records (PixelXDimension, PixelYDimension), pixels;
            a copy downscaled after capture often keeps the original's, which tells what a ground-control file
            measured on the originals refers to (:mod:`..georef.gcp_scale`).
    """

    capture_time: str | None = None
    latitude: float | None = None
    longitude: float | None = None
    altitude_m: float | None = None
    relative_altitude_m: float | None = None
    flight_yaw_deg: float | None = None
    gimbal_yaw_deg: float | None = None
    gimbal_pitch_deg: float | None = None
    focal_length_mm: float | None = None
    focal_length_35mm: float | None = None
    camera: str | None = None
    original_width: int | None = None
    original_height: int | None = None

    @property
    def has_gps(self) -> bool:
        return self.latitude is not None and self.longitude is not None

    def to_json(self) -> dict[str, Any]:
        """The fields that are known, JSON-ready (for the sidecar)."""
        return {key: value for key, value in asdict(self).items() if value is not None}


def read_metadata(path: str | Path) -> FrameMetadata:
    """The metadata of an image file; never raises for a file without it or with a malformed block."""
    from PIL import Image

    values: dict[str, Any] = {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's "Corrupt EXIF data": damaged metadata counts as none
            with Image.open(path) as image:
                exif = image.getexif()
                sub = exif.get_ifd(_EXIF_IFD)
                values["capture_time"] = _text(sub.get(_DATE_TIME_ORIGINAL)) or _text(exif.get(_DATE_TIME))
                values["focal_length_mm"] = _number(sub.get(_FOCAL_LENGTH))
                values["focal_length_35mm"] = _number(sub.get(_FOCAL_35MM))
                values["camera"] = camera_name(_text(exif.get(_MAKE)), _text(exif.get(_MODEL)))
                values["original_width"], values["original_height"] = _dimension(sub.get(_PIXEL_X)), _dimension(sub.get(_PIXEL_Y))
                values.update(_gps(exif.get_ifd(_GPS_IFD)))
    except Exception:  # noqa: BLE001 - Pillow raises many types for damaged headers; metadata is optional
        pass
    values.update(_dji_xmp(path))
    return FrameMetadata(**{k: v for k, v in values.items() if v is not None})


def camera_name(make: str | None, model: str | None) -> str | None:
    """Make and model as one name, the make left out when the model already starts with it (Canon writes
    make "Canon", model "Canon PowerShot ELPH 300 HS")."""
    if make and model and model.lower().startswith(make.lower()):
        return model
    return " ".join(t for t in (make, model) if t) or None


def _dimension(value) -> int | None:
    number = _number(value)
    return int(number) if number is not None and 0 < number < 1_000_000 and number == int(number) else None


def capture_time(path: str | Path) -> str | None:
    """The EXIF capture time of an image file as ``"YYYY:MM:DD HH:MM:SS"``, or None."""
    return read_metadata(path).capture_time


def _gps(gps: dict) -> dict[str, float | None]:
    """Latitude, longitude (signed degrees) and altitude (m) from an EXIF GPS block; None where absent."""
    found: dict[str, float | None] = {}
    for key, value_tag, ref_tag, negative in (("latitude", 2, 1, "S"), ("longitude", 4, 3, "W")):
        degrees = _dms(gps.get(value_tag))
        if degrees is not None and -180.0 <= degrees <= 180.0:
            found[key] = -degrees if _text(gps.get(ref_tag)) == negative else degrees
    altitude = _number(gps.get(6))
    if altitude is not None:
        below = gps.get(5) in (1, b"\x01")  # AltitudeRef 1: below sea level
        found["altitude_m"] = -altitude if below else altitude
    if "latitude" in found and abs(found["latitude"]) > 90.0:
        found.pop("latitude")
    # A receiver without a fix writes 0, 0 (or status "V", void): that is no position, not the Gulf of Guinea.
    if (found.get("latitude") == 0.0 and found.get("longitude") == 0.0) or _text(gps.get(9)) == "V":
        found.pop("latitude", None)
        found.pop("longitude", None)
    return found


def _dms(value) -> float | None:
    try:
        d, m, s = (float(v) for v in value)
    except (TypeError, ValueError):
        return None
    total = d + m / 60.0 + s / 3600.0
    return total if total == total else None  # NaN from a zero denominator


def _number(value) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if number == number and abs(number) != float("inf") else None


def _text(value) -> str | None:
    if isinstance(value, bytes):
        value = value.decode("ascii", "ignore")
    if not isinstance(value, str):
        return None
    value = value.replace("\x00", "").strip()
    return value or None


def _dji_xmp(path: str | Path) -> dict[str, float]:
    keys = {b"RelativeAltitude": "relative_altitude_m", b"FlightYawDegree": "flight_yaw_deg",
            b"GimbalYawDegree": "gimbal_yaw_deg", b"GimbalPitchDegree": "gimbal_pitch_deg"}
    try:
        with open(path, "rb") as handle:
            head = handle.read(_XMP_SCAN_BYTES)
    except OSError:
        return {}
    found = {}
    for name, value in _DJI.findall(head):
        number = _number(value.decode("ascii", "ignore"))
        if name in keys and number is not None:
            found[keys[name]] = number
    return found
