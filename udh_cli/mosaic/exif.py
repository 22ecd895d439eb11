"""Just enough EXIF to order frames by capture time, with no imaging library: ``DateTimeOriginal``."""

from __future__ import annotations

import struct
from pathlib import Path

_EXIF_IFD_POINTER = 0x8769
_DATE_TIME_ORIGINAL = 0x9003
_DATE_TIME = 0x0132


def capture_time(path: str | Path) -> str | None:
    """The EXIF capture time of a JPEG or TIFF file as ``"YYYY:MM:DD HH:MM:SS"``, or ``None``.

    Prefers ``DateTimeOriginal`` and falls back to ``DateTime``. Never raises for a malformed file.
    """
    try:
        with open(path, "rb") as handle:
            head = handle.read(256 * 1024)  # EXIF lives in the first 64 KiB of a JPEG; TIFF IFD0 near the start
        tiff = _tiff_block(head)
        return None if tiff is None else _read_time(tiff)
    except (OSError, struct.error, IndexError, UnicodeDecodeError, ValueError):
        return None


def _tiff_block(data: bytes) -> bytes | None:
    """The TIFF structure holding the EXIF tags: a JPEG's APP1 payload, or a TIFF file itself."""
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return data
    if data[:2] != b"\xff\xd8":
        return None
    position = 2
    while position + 4 <= len(data) and data[position] == 0xFF:
        marker = data[position + 1]
        length = struct.unpack(">H", data[position + 2 : position + 4])[0]
        if marker == 0xE1 and data[position + 4 : position + 10] == b"Exif\x00\x00":
            return data[position + 10 : position + 2 + length]
        if marker == 0xDA:  # start of scan: no EXIF before the image data
            return None
        position += 2 + length
    return None


def _read_time(tiff: bytes) -> str | None:
    order = "<" if tiff[:2] == b"II" else ">"
    tags = _ifd(tiff, order, struct.unpack(order + "I", tiff[4:8])[0])
    exif = _ifd(tiff, order, tags[_EXIF_IFD_POINTER][2]) if _EXIF_IFD_POINTER in tags else {}
    for source, tag in ((exif, _DATE_TIME_ORIGINAL), (tags, _DATE_TIME)):
        if tag in source:
            kind, count, value_offset = source[tag]
            if kind == 2 and count >= 19:
                text = tiff[value_offset : value_offset + 19].decode("ascii")
                if text.strip(" \x00:"):
                    return text
    return None


def _ifd(tiff: bytes, order: str, offset: int) -> dict[int, tuple[int, int, int]]:
    """Tags of one IFD: tag -> (type, count, value or offset)."""
    count = struct.unpack(order + "H", tiff[offset : offset + 2])[0]
    entries = {}
    for index in range(count):
        start = offset + 2 + 12 * index
        tag, kind, n, value = struct.unpack(order + "HHII", tiff[start : start + 12])
        entries[tag] = (kind, n, value)
    return entries
