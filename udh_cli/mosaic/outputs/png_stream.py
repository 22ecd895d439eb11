"""A mosaic's PNG written band by band while its tiles are blended, compressed on another thread.

OpenCV encodes a PNG from the whole image at once, on the calling thread, after compositing. Here each band of
canvas rows is filtered and compressed as soon as its tiles are blended, so the compression runs beside the
next tiles' blending, and the map is never assembled whole for the PNG. The encoding is OpenCV's: the PNG "Sub"
filter on every row, zlib level 1 with the run-length strategy, so the files are OpenCV's size (the tests hold
it). Each block of rows is compressed as a raw DEFLATE stream ended by a sync flush, so that the blocks
concatenate into one zlib stream (as pigz does); the run-length strategy only matches the byte before, so
cutting costs no compression.
"""

from __future__ import annotations

import contextlib
import struct
import zlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import BinaryIO, Iterable, Iterator

import cv2
import numpy as np

from udh_cli.errors import UdhError

SIGNATURE = b"\x89PNG\r\n\x1a\n"
ZLIB_HEADER = b"\x78\x01"  # deflate, 32 KB window, "fastest" level: what level 1 writes
BLOCK_BYTES = 4 * 2**20  # uncompressed bytes per compressed block: a few MB keeps the threads busy and the memory small
MAX_PENDING_BLOCKS = 4  # blocks compressed ahead of the file; bounds the memory the writer holds
MAX_PNG_SIDE = 2**31 - 1  # the format's limit on width and height


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


def _filtered(rows: np.ndarray) -> bytes:
    """(h, w, 4) BGRA or (h, w, 3) BGR uint8 rows as PNG scanlines: RGB(A), each row's filter byte (1, "Sub")
    then each byte minus the byte one pixel to its left (mod 256)."""
    height, width, channels = rows.shape
    rgb = cv2.cvtColor(rows, cv2.COLOR_BGRA2RGBA if channels == 4 else cv2.COLOR_BGR2RGB)
    lines = np.empty((height, 1 + width * channels), np.uint8)
    lines[:, 0] = 1
    body = lines[:, 1:].reshape(height, width, channels)
    body[:, 0] = rgb[:, 0]
    np.subtract(rgb[:, 1:], rgb[:, :-1], out=body[:, 1:])  # uint8 arithmetic wraps, as the filter's mod 256 does
    return lines.tobytes()


def _compressed(raw: bytes, last: bool) -> tuple[bytes, int, int]:
    """``raw`` as a raw DEFLATE block sequence ending on a byte boundary (the stream's end when ``last``), with
    the Adler-32 of ``raw`` and its length, which :func:`_adler32_combine` joins in order."""
    packer = zlib.compressobj(1, zlib.DEFLATED, -15, 8, zlib.Z_RLE)
    data = packer.compress(raw) + packer.flush(zlib.Z_FINISH if last else zlib.Z_FULL_FLUSH)
    return data, zlib.adler32(raw), len(raw)


def _adler32_combine(first: int, second: int, second_length: int) -> int:
    """The Adler-32 of two byte strings joined, from each one's checksum and the second's length (zlib's
    ``adler32_combine``, which Python's zlib does not expose)."""
    base = 65521
    remainder = second_length % base
    sum1 = first & 0xFFFF
    sum2 = (remainder * sum1) % base
    sum1 += (second & 0xFFFF) + base - 1
    sum2 += ((first >> 16) & 0xFFFF) + ((second >> 16) & 0xFFFF) + base - remainder
    return ((sum2 % base) << 16) | (sum1 % base)


class StreamedPng:
    """A PNG of ``size`` (width, height), 8 bits per channel, RGBA (``channels`` 4, from BGRA rows) or RGB (3,
    from BGR), written to ``path`` band by band: :meth:`add_rows` in order from the top, then :meth:`close`.
    Blocks of rows are compressed on ``threads`` threads (zlib releases the GIL) while the caller goes on."""

    def __init__(self, path: str | Path, size: tuple[int, int], channels: int = 4, threads: int = 1) -> None:
        width, height = size
        if not (0 < width <= MAX_PNG_SIDE and 0 < height <= MAX_PNG_SIDE) or channels not in (3, 4):
            raise UdhError(f"{path}: a PNG cannot hold a {width}x{height} image with {channels} channels")
        self.path = Path(path)
        self.size = size
        self.channels = channels
        self.next_row = 0
        self.adler = 1
        self.pending: deque[Future] = deque()
        self.rows_per_block = max(1, BLOCK_BYTES // (width * channels + 1))
        try:
            self.file: BinaryIO = open(self.path, "wb")
        except OSError as exc:
            raise UdhError(f"{path}: cannot write the mosaic ({exc.strerror or exc}); check the folder's permissions and free space") from None
        self.pool = ThreadPoolExecutor(max(1, threads), thread_name_prefix="udh-png")
        colour_type = 6 if channels == 4 else 2
        self._write(SIGNATURE + _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)))
        self.idat_started = False

    def add_rows(self, top: int, rows: np.ndarray) -> None:
        """Add the canvas rows starting at row ``top``: (h, width, channels) uint8, BGRA or BGR. Rows come in order."""
        height = rows.shape[0]
        if top != self.next_row or rows.shape[1:] != (self.size[0], self.channels) or rows.dtype != np.uint8:
            raise UdhError(f"{self.path}: rows {top}-{top + height} of shape {rows.shape} {rows.dtype} do not continue the PNG at row "
                           f"{self.next_row} ({self.size[0]} px wide, {self.channels} channels); this is a bug in udh, please report it")
        for start in range(0, height, self.rows_per_block):
            block = rows[start : start + self.rows_per_block]
            self.next_row += block.shape[0]
            last = self.next_row == self.size[1]
            self.pending.append(self.pool.submit(lambda b=block, end=last: _compressed(_filtered(b), end)))
            self._drain(MAX_PENDING_BLOCKS)

    def close(self) -> None:
        """Write what is still being compressed and the end of the file; refuses a PNG missing rows."""
        try:
            if self.next_row != self.size[1]:
                raise UdhError(f"{self.path}: the PNG got {self.next_row} of its {self.size[1]} rows; this is a bug in udh, please report it")
            self._drain(0)
            self._write(_chunk(b"IDAT", struct.pack(">I", self.adler)) + _chunk(b"IEND", b""), flush=True)
        finally:
            self.abandon()

    def abandon(self) -> None:
        """Stop: the file is left incomplete, for its staging folder to discard."""
        for future in self.pending:
            future.cancel()
        self.pool.shutdown(wait=True)
        with contextlib.suppress(OSError):  # closing flushes what a full disk refused again; the file is discarded anyway
            self.file.close()

    def __enter__(self) -> "StreamedPng":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.close()
        else:
            self.abandon()

    def _drain(self, keep: int) -> None:
        """Write finished blocks in order until at most ``keep`` are pending (waiting for the oldest when over)."""
        while self.pending and (len(self.pending) > keep or self.pending[0].done()):
            data, adler, length = self.pending.popleft().result()
            if not self.idat_started:
                data = ZLIB_HEADER + data
                self.idat_started = True
            self.adler = _adler32_combine(self.adler, adler, length)
            self._write(_chunk(b"IDAT", data))

    def _write(self, data: bytes, flush: bool = False) -> None:
        try:
            self.file.write(data)
            if flush:  # a small file sits whole in the buffer: the full disk shows only here
                self.file.flush()
        except OSError as exc:  # a full disk: one line, and the staging folder discards the file
            raise UdhError(f"{self.path}: writing the mosaic failed ({exc.strerror or exc}); check the free space and permissions") from None


def bands(tiles: Iterable[tuple[tuple[int, int, int, int], np.ndarray]], size: tuple[int, int]) -> Iterator[tuple[int, np.ndarray]]:
    """Row-major canvas ``tiles`` (``((x0, y0, x1, y1), (h, w, c) array)``, as :func:`.composite.composite_tiles`
    yields them) joined into full-width bands: ``(top, (h, width, c) array)`` per row of tiles."""
    width = size[0]
    band, top, bottom = None, 0, 0
    for (x0, y0, x1, y1), tile in tiles:
        if band is not None and (y0, y1) != (top, bottom):
            yield top, band
            band = None
        if band is None:
            band, top, bottom = np.zeros((y1 - y0, width) + tile.shape[2:], tile.dtype), y0, y1
        band[:, x0:x1] = tile
    if band is not None:
        yield top, band
