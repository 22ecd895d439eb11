"""Reading images (errors, bit depths, EXIF) and writing outputs atomically."""

from __future__ import annotations

import os
import struct
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from udh_cli import images
from udh_cli.errors import UdhError
from udh_cli.images import atomic_write_bytes, read_image, to_bgr_u8, to_gray_float, to_gray_u8, write_image


def encoded(image: np.ndarray, suffix: str = ".png") -> bytes:
    ok, data = cv2.imencode(suffix, image)
    assert ok
    return data.tobytes()


def with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """``jpeg`` with an EXIF APP1 segment holding only the orientation tag (0x0112), inserted after SOI."""
    tiff = b"MM\x00\x2a" + struct.pack(">I", 8) + struct.pack(">H", 1)
    tiff += struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack(">I", 0)
    payload = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + jpeg[2:]


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("missing.png", None, "no such file"),
        ("empty.png", b"", "empty"),
        ("text.png", b"this is not an image\n" * 20, "not a readable image"),
        ("truncated.png", "truncated", "not a readable image"),
        ("tiny.png", "1x1", "1x1 pixels"),
        ("thin.png", "100x3", "100x3 pixels"),
    ],
)
def test_read_image_errors(tmp_path, capfd, name, content, message):
    path = tmp_path / name
    if content == "truncated":
        content = encoded(np.random.default_rng(0).integers(0, 255, (64, 64), dtype=np.uint8))[:80]
    elif content == "1x1":
        content = encoded(np.zeros((1, 1), np.uint8))
    elif content == "100x3":
        content = encoded(np.zeros((3, 100), np.uint8))
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(UdhError, match=message) as error:
        read_image(path)
    assert "\n" not in str(error.value) and str(path) in str(error.value)
    # The codecs' own complaints ("libpng error", OpenCV WARN lines) do not reach the terminal.
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == ""


def test_read_image_of_a_folder(tmp_path):
    with pytest.raises(UdhError, match="folder"):
        read_image(tmp_path)


def test_read_image_corrupt_data_prints_nothing(tmp_path, capfd):
    data = bytearray(encoded(np.random.default_rng(1).integers(0, 255, (64, 64), dtype=np.uint8)))
    data[60:90] = b"\x00" * 30  # break the compressed stream: libpng reports "incorrect data check"
    (tmp_path / "corrupt.png").write_bytes(bytes(data))
    with pytest.raises(UdhError, match="not a readable image"):
        read_image(tmp_path / "corrupt.png")
    assert capfd.readouterr().err == ""


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root can read anything")
def test_read_image_unreadable(tmp_path):
    path = tmp_path / "locked.png"
    path.write_bytes(encoded(np.zeros((16, 16), np.uint8)))
    path.chmod(0)
    with pytest.raises(UdhError, match="permissions"):
        read_image(path)


@pytest.mark.parametrize("shape", [(30, 40), (30, 40, 3)])
def test_16_bit_png_round_trip(tmp_path, shape):
    image = np.random.default_rng(2).integers(0, 65536, shape, dtype=np.uint16)
    write_image(tmp_path / "deep.png", image)
    back = read_image(tmp_path / "deep.png")
    assert back.dtype == np.uint16 and back.shape == shape
    np.testing.assert_array_equal(back, image)


def test_8_bit_grey_stays_grey_and_alpha_is_dropped(tmp_path):
    grey = np.random.default_rng(3).integers(0, 256, (20, 30), dtype=np.uint8)
    write_image(tmp_path / "grey.png", grey)
    np.testing.assert_array_equal(read_image(tmp_path / "grey.png"), grey)
    bgra = np.random.default_rng(3).integers(0, 256, (20, 30, 4), dtype=np.uint8)
    write_image(tmp_path / "bgra.png", bgra)
    np.testing.assert_array_equal(read_image(tmp_path / "bgra.png"), bgra[..., :3])


def test_exif_orientation_is_applied(tmp_path):
    # Orientation 6: the stored pixels must be turned 90 degrees clockwise to display upright.
    stored = np.zeros((40, 60, 3), np.uint8)
    stored[:10, :10] = 255  # a white block at the stored top-left
    path = tmp_path / "rotated.jpg"
    path.write_bytes(with_exif_orientation(encoded(stored, ".jpg"), 6))
    shown = read_image(path)
    assert shown.shape == (60, 40, 3)
    assert shown[:10, -10:].mean() > 200 and shown[:10, :10].mean() < 50  # now at the top-right


def test_conversions():
    u8 = np.array([[0, 255], [51, 102]], np.uint8).repeat(8, 0).repeat(8, 1)
    np.testing.assert_allclose(to_gray_float(u8)[::8, ::8], [[0, 1], [0.2, 0.4]], atol=1e-7)
    u16 = (u8.astype(np.uint16) * 257).astype(np.uint16)
    np.testing.assert_allclose(to_gray_float(u16), to_gray_float(u8), atol=1e-7)
    np.testing.assert_array_equal(to_gray_u8(u16), u8)
    np.testing.assert_array_equal(to_bgr_u8(u16), cv2.cvtColor(u8, cv2.COLOR_GRAY2BGR))
    colour = np.dstack([u8, np.zeros_like(u8), np.zeros_like(u8)])  # pure blue, BGR
    np.testing.assert_allclose(to_gray_float(colour)[0, 8], 0.114, atol=2e-3)
    # Other integer depths (signed 16-bit, 32-bit TIFF) also land in [0, 1].
    i16 = np.full((16, 16), 16384, np.int16)
    assert to_gray_float(i16).max() == pytest.approx(0.5, abs=1e-4)
    assert to_bgr_u8(i16).max() == 128


def test_stretch_for_16_bit_data_that_fills_a_small_range():
    narrow = (1000 + np.arange(256, dtype=np.uint16).reshape(16, 16) * 10).astype(np.uint16)  # 1000..3550
    assert to_gray_u8(narrow).max() - to_gray_u8(narrow).min() < 15  # plain conversion: a dozen grey levels
    stretched = to_gray_u8(narrow, stretch=True)
    assert stretched.min() == 0 and stretched.max() == 255
    flat = np.full((16, 16), 1234, np.uint16)
    np.testing.assert_array_equal(to_gray_u8(flat, stretch=True), to_gray_u8(flat))


def test_atomic_write_leaves_no_temp_files_and_keeps_the_old_file_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "out.bin"
    atomic_write_bytes(target, b"first")
    assert target.read_bytes() == b"first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]
    # Output files get the usual permissions, not mkstemp's owner-only 0600.
    umask = os.umask(0o022)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask

    def failing_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(images.os, "replace", failing_replace)
    with pytest.raises(UdhError, match="out.bin: writing it failed \\(No space left on device\\)"):
        atomic_write_bytes(target, b"second")
    assert target.read_bytes() == b"first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]


def test_atomic_write_where_no_file_can_be_created(tmp_path, monkeypatch):
    # A read-only file system passes the os.access check for root; the failure must still be one UdhError.
    def read_only(*args, **kwargs):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(images, "create_new", read_only)
    with pytest.raises(UdhError, match="out.bin: cannot create a file in .*Read-only file system"):
        atomic_write_bytes(tmp_path / "out.bin", b"x")
    assert list(tmp_path.iterdir()) == []


def test_an_interrupt_just_after_the_temporary_file_appears_leaves_nothing(tmp_path, monkeypatch):
    # Ctrl-C or SIGTERM (handled as Ctrl-C) between the file's creation and its name reaching the writer.
    created = images.create_new

    def create_then_interrupt(path):
        os.close(created(path))
        raise KeyboardInterrupt

    (tmp_path / "out.bin").write_bytes(b"old")
    monkeypatch.setattr(images, "create_new", create_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_bytes(tmp_path / "out.bin", b"new")
    assert [(p.name, p.read_bytes()) for p in tmp_path.iterdir()] == [("out.bin", b"old")]


def test_atomic_write_to_a_missing_folder(tmp_path):
    with pytest.raises(UdhError, match="does not exist"):
        atomic_write_bytes(tmp_path / "no" / "such" / "out.png", b"x")
    assert list(tmp_path.iterdir()) == []


def test_write_image_errors_leave_nothing(tmp_path):
    with pytest.raises(UdhError, match="unknown file type '.gif'; use one of .jpg"):
        write_image(tmp_path / "out.gif", np.zeros((8, 8), np.uint8))
    with pytest.raises(UdhError, match="could not encode"):
        write_image(tmp_path / "out.png", np.zeros((8, 8, 2), np.uint8))
    assert list(tmp_path.iterdir()) == []


def test_write_image_replaces_atomically(tmp_path):
    target = tmp_path / "picture.png"
    write_image(target, np.zeros((8, 8, 3), np.uint8))
    write_image(target, np.full((8, 8, 3), 200, np.uint8))
    assert read_image(target).mean() == 200
    assert [p.name for p in tmp_path.iterdir()] == ["picture.png"]


def test_accepts_path_strings(tmp_path):
    write_image(str(tmp_path / "s.png"), np.zeros((8, 8), np.uint8))
    assert read_image(str(tmp_path / "s.png")).shape == (8, 8)
    assert isinstance(read_image(Path(tmp_path / "s.png")), np.ndarray)


def test_local_contrast_removes_gain_and_bias_that_vary_across_the_image():
    from conftest import textured_image
    from udh_cli.images import local_contrast

    image = textured_image(seed=2).astype(np.float32) / 255
    ys, xs = np.mgrid[0:240, 0:320].astype(np.float32)
    gain, bias = 0.5 + xs / 320, 0.2 * ys / 240  # both change slowly across the image
    plain, lit = local_contrast(image, 4.0), local_contrast(image * gain + bias, 4.0)
    inner = (slice(20, -20), slice(20, -20))
    assert lit.dtype == np.float32 and lit.shape == image.shape
    assert abs(float(plain[inner].mean())) < 0.1 and 0.7 < float(plain[inner].std()) < 1.3
    assert float(np.corrcoef(plain[inner].ravel(), lit[inner].ravel())[0, 1]) > 0.95
    flat = local_contrast(np.full((64, 64), 0.5, np.float32) + np.random.default_rng(0).normal(0, 1e-3, (64, 64)).astype(np.float32), 4.0)
    assert float(np.abs(flat).max()) < 0.5  # the floor keeps sensor noise from becoming texture


def _png_declaring(path, width: int, height: int) -> None:
    """A small PNG whose header declares ``width`` x ``height`` (the pixel data is a few zero rows)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    rows = zlib.compress(b"\x00" * (width + 1) * 4)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", rows) + chunk(b"IEND", b""))


def test_a_decompression_bomb_is_refused_from_its_header(tmp_path, monkeypatch):
    from udh_cli import images
    from udh_cli.images import read_image

    bomb = tmp_path / "bomb.png"
    _png_declaring(bomb, 32000, 32000)
    assert bomb.stat().st_size < 100_000

    def no_decoding(*args, **kwargs):
        raise AssertionError("the bomb was decoded: its header must refuse it first")

    with monkeypatch.context() as patched:
        patched.setattr(images.cv2, "imdecode", no_decoding)
        with pytest.raises(UdhError, match="32000x32000 pixels, over the 250 MP limit"):
            read_image(bomb)
    monkeypatch.setenv("UDH_MAX_PIXELS", "1000")
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((40, 40), np.uint8))
    with pytest.raises(UdhError, match="over the 0 MP limit"):
        read_image(small)
    monkeypatch.setenv("UDH_MAX_PIXELS", "lots")
    with pytest.raises(UdhError, match="give a number of pixels"):
        read_image(small)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_fifo_without_a_writer_does_not_hang(tmp_path):
    from udh_cli.images import read_image

    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    with pytest.raises(UdhError, match="empty"):
        read_image(fifo)


def test_image_files_are_bounded_by_size_before_they_are_read(tmp_path, monkeypatch):
    import threading

    from udh_cli.images import max_file_bytes

    monkeypatch.setenv("UDH_MAX_PIXELS", "64")
    sparse = tmp_path / "huge.png"
    with open(sparse, "wb") as handle:
        handle.truncate(max_file_bytes() + 1)  # no data is written: the size alone must refuse it
    with pytest.raises(UdhError, match="larger than any image udh reads"):
        read_image(sparse)
    if not hasattr(os, "mkfifo"):
        return
    pipe = tmp_path / "piped.png"
    os.mkfifo(pipe)

    def endless_writer() -> None:  # cat /dev/zero > piped.png
        try:
            with open(pipe, "wb") as handle:
                while True:
                    handle.write(bytes(1 << 20))
        except (BrokenPipeError, OSError):
            pass

    keeper = os.open(pipe, os.O_RDONLY | os.O_NONBLOCK)  # a reader already there, so that the writer's open returns
    writer = threading.Thread(target=endless_writer, daemon=True)
    writer.start()
    time.sleep(0.2)
    try:
        with pytest.raises(UdhError, match="more than any image udh reads"):
            read_image(pipe)
    finally:
        os.close(keeper)  # the last reader gone: the writer's next write fails and it ends
    writer.join(timeout=10)
    assert not writer.is_alive()


def test_an_encoder_failure_is_one_line_with_the_codecs_words_off_stderr(tmp_path, monkeypatch, capfd):
    def failing_encoder(suffix, image, *args):  # what OpenCV's TIFF encoder does on a full disk
        os.write(2, b"TIFFAppendToStrip: Write error at scanline 12.\n")
        return False, None

    monkeypatch.setattr(images.cv2, "imencode", failing_encoder)
    with pytest.raises(UdhError, match=r"could not encode .* \(TIFFAppendToStrip: Write error at scanline 12\.\); check the free space"):
        write_image(tmp_path / "m.tif", np.zeros((16, 16, 3), np.uint8))
    assert capfd.readouterr().err == "" and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("image", "pixel_bytes"), [(np.zeros((480, 640), np.uint8), 1), (np.zeros((480, 640, 4), np.uint8), 3),
                                                  (np.zeros((480, 640, 3), np.uint16), 6)], ids=["grey8", "rgba8", "colour16"])
def test_an_image_is_decoded_only_when_the_memory_free_can_hold_what_the_decode_makes(image, pixel_bytes, tmp_path, monkeypatch):
    path = tmp_path / "a.png"
    cv2.imwrite(str(path), image)
    needed = 640 * 480 * pixel_bytes + path.stat().st_size  # the decoded pixels (alpha dropped) and the file's bytes
    monkeypatch.setenv("UDH_MEMORY_BUDGET", str(needed - 1))

    def forbidden(*args, **kwargs):
        raise AssertionError("decoded although it cannot fit")

    monkeypatch.setattr(cv2, "imdecode", forbidden)
    with pytest.raises(UdhError, match=r"decoding its 640x480 pixels needs about .* downscale the image"):
        images.read_image(path)
    monkeypatch.undo()
    monkeypatch.setenv("UDH_MEMORY_BUDGET", str(needed))
    decoded = images.read_image(path)
    assert decoded.shape[:2] == (480, 640) and decoded.nbytes == 640 * 480 * pixel_bytes
