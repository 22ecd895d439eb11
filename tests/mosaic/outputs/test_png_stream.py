"""The streamed PNG writer: the file decodes to the rows given, its checksums hold, and its size is OpenCV's."""

from __future__ import annotations

import os
import struct
import zlib

import cv2
import numpy as np
import pytest

from udh_cli.errors import UdhError
from udh_cli.mosaic.outputs import png_stream
from udh_cli.mosaic.outputs.png_stream import StreamedPng, bands


def _map_like(height: int, width: int, channels: int = 4, seed: int = 0) -> np.ndarray:
    """A smooth image with texture and a transparent border, like a mosaic's."""
    rng = np.random.default_rng(seed)
    image = cv2.resize(rng.integers(0, 256, (height // 8 + 1, width // 8 + 1, 3), dtype=np.uint8), (width, height))
    image = cv2.add(image, rng.integers(0, 12, image.shape, dtype=np.uint8))
    if channels == 3:
        return image
    alpha = np.zeros((height, width), np.uint8)
    alpha[height // 10 : -height // 10, width // 7 : -width // 9] = 255
    return np.dstack([image * (alpha[..., None] > 0), alpha])


def _idat(data: bytes) -> bytes:
    """The zlib stream of a PNG: its IDAT chunks joined, each chunk's CRC checked."""
    position, joined = 8, b""
    while position < len(data):
        length, = struct.unpack(">I", data[position : position + 4])
        kind, body = data[position + 4 : position + 8], data[position + 8 : position + 8 + length]
        crc, = struct.unpack(">I", data[position + 8 + length : position + 12 + length])
        assert crc == zlib.crc32(kind + body)
        if kind == b"IDAT":
            joined += body
        position += 12 + length
    return joined


@pytest.mark.parametrize("channels", [4, 3])
def test_written_in_bands_it_decodes_to_the_rows_and_its_checksum_holds(tmp_path, monkeypatch, channels):
    monkeypatch.setattr(png_stream, "BLOCK_BYTES", 50_000)  # many blocks, so that their joins are exercised
    image = _map_like(301, 257, channels)
    path = tmp_path / "map.png"
    with StreamedPng(path, (257, 301), channels, threads=2) as png:
        for top in range(0, 301, 64):
            png.add_rows(top, image[top : top + 64])
    assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), image)
    raw = zlib.decompress(_idat(path.read_bytes()))  # checks the stream's Adler-32, joined from the blocks'
    assert len(raw) == 301 * (1 + 257 * channels)


def test_its_size_is_opencvs_within_half_a_percent(tmp_path):
    image = _map_like(600, 800)
    path = tmp_path / "map.png"
    with StreamedPng(path, (800, 600)) as png:
        png.add_rows(0, image)
    ours, opencv = path.stat().st_size, len(cv2.imencode(".png", image)[1])
    assert abs(ours - opencv) / opencv < 0.005


@pytest.mark.parametrize("lengths", [(1, 1), (7, 70_000), (65_521, 3), (200_000, 131_071)])
def test_adler32_combine_is_the_checksum_of_the_joined_bytes(lengths):
    rng = np.random.default_rng(sum(lengths))
    first, second = (rng.integers(0, 256, n, dtype=np.uint8).tobytes() for n in lengths)
    assert png_stream._adler32_combine(zlib.adler32(first), zlib.adler32(second), len(second)) == zlib.adler32(first + second)


def test_bands_join_row_major_tiles_into_full_width_rows():
    image = _map_like(50, 70)
    tiles = [((x, y, min(x + 32, 70), min(y + 32, 50)), image[y : y + 32, x : x + 32]) for y in (0, 32) for x in (0, 32, 64)]
    joined = list(bands(tiles, (70, 50)))
    assert [top for top, _ in joined] == [0, 32]
    assert np.array_equal(np.concatenate([band for _, band in joined]), image)


def test_rows_out_of_order_or_missing_are_refused_and_the_file_is_left_to_its_staging(tmp_path):
    image = _map_like(64, 40)
    with pytest.raises(UdhError, match="do not continue the PNG at row 0"):
        with StreamedPng(tmp_path / "a.png", (40, 64)) as png:
            png.add_rows(32, image[32:])
    with pytest.raises(UdhError, match="got 32 of its 64 rows"):
        with StreamedPng(tmp_path / "b.png", (40, 64)) as png:
            png.add_rows(0, image[:32])
    with pytest.raises(UdhError, match="cannot hold a 0x64 image"):
        StreamedPng(tmp_path / "c.png", (0, 64))


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full, a device that is always full")
@pytest.mark.parametrize("height", [4, 2000])  # one within the file's buffer (fails on flush), one past it (on write)
def test_a_full_disk_is_one_udh_error_not_an_oserror(height):
    with pytest.raises(UdhError, match="writing the mosaic failed .*No space left"):
        with StreamedPng("/dev/full", (64, height)) as png:
            png.add_rows(0, _map_like(height, 64))
