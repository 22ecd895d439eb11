"""Reading images from disk, turning them into the grey float arrays the estimators use, and writing
output files atomically."""

from __future__ import annotations

import contextlib
import os
import secrets
import sys
import tempfile
import threading
import warnings
from pathlib import Path

import cv2
import numpy as np

from udh_cli.errors import UdhError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
MIN_IMAGE_SIDE = 8  # pixels; below this no estimator can say anything useful

_PILLOW_LOCK = threading.Lock()
MAX_PIXELS_ENV = "UDH_MAX_PIXELS"
DEFAULT_MAX_PIXELS = 250_000_000  # 250 MP: a 16,000 x 15,000 frame; far above any drone camera, far below a bomb
# Huffman-coded JPEG spends at least about 2 bits on each 8x8 block (256 pixels a byte); far more pixels a byte
# is a truncated file or a forged header, whose decoder would invent the missing pixels.
MAX_JPEG_PIXELS_PER_BYTE = 4096


def max_pixels() -> int:
    """The largest image (width x height) udh decodes: ``UDH_MAX_PIXELS`` if set, else 250 MP."""
    value = os.environ.get(MAX_PIXELS_ENV)
    if value is None:
        return DEFAULT_MAX_PIXELS
    try:
        limit = int(float(value))
    except ValueError:
        raise UdhError(f"{MAX_PIXELS_ENV}={value!r}: give a number of pixels, e.g. 400000000") from None
    if limit < MIN_IMAGE_SIDE**2:
        raise UdhError(f"{MAX_PIXELS_ENV}={value!r}: give at least {MIN_IMAGE_SIDE**2} pixels")
    return limit


def image_size_from_header(data: bytes | np.ndarray) -> tuple[int, int] | None:
    """``(width, height)`` from an encoded image's header, without decoding its pixels; None if unknown.

    Pillow reads only the header here (``Image.open`` is lazy). Why not OpenCV: ``cv2.imdecode`` allocates
    the whole image before it can say how large it is, and a 1 MB PNG can declare 32,000 x 32,000 pixels.
    """
    header = _image_header(data)
    return None if header is None else header[:2]


def _image_header(data: bytes | np.ndarray) -> tuple[int, int, int] | None:
    """``(width, height, bytes a pixel)`` of an encoded image from its header, None if unknown; the bytes a
    pixel are what :func:`read_image`'s decode makes of it: grey 1 channel, else 3 (alpha is dropped), each
    sample 1, 2 or 4 bytes as stored."""
    import io

    from PIL import Image, UnidentifiedImageError

    with _PILLOW_LOCK:
        # Pillow's own bomb check raises before it says the size; udh applies its own limit to the size.
        saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # Pillow's "Corrupt EXIF data" while it reads the DPI: not the size
                with Image.open(io.BytesIO(bytes(data))) as header:
                    return (*header.size, _decoded_bytes_per_pixel(header, bytes(data[:32])))
        except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
            return None
        finally:
            Image.MAX_IMAGE_PIXELS = saved


def _decoded_bytes_per_pixel(header, start: bytes) -> int:
    """Bytes a pixel of ``cv2.imdecode(ANYDEPTH | ANYCOLOR)`` for the Pillow image ``header`` whose file starts
    with ``start``. Why not Pillow's mode alone: it says "RGB" for 16-bit colour PNG and TIFF."""
    channels = 1 if header.mode in ("1", "L", "I", "F") or header.mode.startswith("I;16") else 3
    if header.mode in ("I", "F"):
        bits = 32
    elif start.startswith(b"\x89PNG") and len(start) > 24:
        bits = start[24]  # IHDR's bit depth
    elif header.format == "TIFF":
        try:
            bits = max(int(sample) for sample in header.tag_v2.get(258, (8,)))  # BitsPerSample
        except (TypeError, ValueError):  # a forged tag: count the widest sample OpenCV makes
            bits = 32
    else:
        bits = 16 if header.mode.startswith("I;16") else 8
    return channels * (2 if bits == 16 else 4 if bits > 16 else 1)


def max_file_bytes() -> int:
    """The largest image file udh reads: :func:`max_pixels` of uncompressed 16-bit RGBA, plus room for metadata."""
    return max_pixels() * 8 + (64 << 20)


def _read_bytes(path: Path, limit: int) -> bytes:
    """The file's bytes, at most ``limit`` (:class:`UdhError` past it, before reading a regular file); pipes
    (``<(cat a.png)``) are read as they come, and a FIFO without a writer is empty.

    A FIFO opened without O_NONBLOCK waits for a writer for ever; opened with it, it reads at once what a
    writer has sent (a process substitution) or nothing (no writer), and the blocking reads that follow end
    at the writer's end of file.
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0)
    fd = os.open(path, flags)
    try:
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        if os.fstat(fd).st_size > limit:
            raise UdhError(f"{path}: {os.fstat(fd).st_size >> 20} MiB, larger than any image udh reads ({limit >> 20} MiB); "
                           f"check the file, or raise {MAX_PIXELS_ENV} if it is a real image")
        chunks, total = [], 0
        while True:
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                return b"".join(chunks)
            chunks.append(chunk)
            total += len(chunk)
            if total > limit:  # a pipe that does not end (cat /dev/zero |)
                raise UdhError(f"{path}: more than {limit >> 20} MiB came through it, more than any image udh reads; "
                               f"check what writes to it")
    finally:
        os.close(fd)


def shown_path(path: str | os.PathLike, limit: int = 160) -> str:
    """``path`` for a one-line message: whole when short, else its start and end around an ellipsis."""
    text = str(path)
    return text if len(text) <= limit else f"{text[: limit // 2 - 2]}...{text[-(limit // 2 - 2):]} ({len(os.fsencode(text))} bytes)"


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as it is stored: (H, W) or (H, W, 3) BGR, 8- or 16-bit (or float for EXR/TIFF).

    EXIF orientation is applied, so the pixels come out the way a viewer shows them. The header's size is
    checked against :func:`max_pixels` before any pixel is decoded.
    Raises :class:`UdhError` for a missing, unreadable, non-image, empty, oversized or tiny file.
    """
    import stat

    path = Path(path)
    try:
        exists, is_dir = path.exists(), path.is_dir()
    except OSError as exc:  # e.g. a name longer than the file system takes (ENAMETOOLONG)
        raise UdhError(f"{shown_path(path)}: cannot use this path ({exc.strerror or exc}); give a shorter or correct one") from None
    if not exists:
        raise UdhError(f"{path}: no such file; check the path")
    if is_dir:
        raise UdhError(f"{path}: is a folder, not an image file")
    try:
        mode = path.stat().st_mode
        if not (stat.S_ISREG(mode) or stat.S_ISFIFO(mode)):
            raise UdhError(f"{path}: not a regular file (a device or socket); give a JPEG, PNG or TIFF file")
        data = _read_bytes(path, max_file_bytes())
    except OSError as exc:
        raise UdhError(f"{path}: cannot read it ({exc.strerror or exc}); check its permissions") from None
    if len(data) == 0:
        raise UdhError(f"{path}: the file is empty; give a JPEG, PNG or TIFF image")
    check_declared_pixels(path, data)
    limit = max_pixels()
    # ANYDEPTH keeps 16-bit data; ANYCOLOR keeps grey as grey. Without IGNORE_ORIENTATION, EXIF is applied.
    messages: list[str] = []
    try:
        with native_messages_silenced(messages):
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    except cv2.error:  # e.g. beyond OpenCV's pixel limit, or a codec that rejects the stream outright
        image = None
    if image is None:
        raise UdhError(f"{path}: not a readable image; give a JPEG, PNG or TIFF file")
    damage = next((line.strip() for line in messages if line.lstrip().startswith(DAMAGE_MESSAGES)), None)
    if damage is not None:  # the decoder went on, filling what it could not read: the pixels are not the photo's
        raise UdhError(f"{path}: the file is damaged (the decoder says: {damage[:120]}); copy it again from the camera")
    if image.shape[0] * image.shape[1] > limit:  # a format whose header Pillow could not read
        raise UdhError(f"{path}: {image.shape[1]}x{image.shape[0]} pixels, over the {limit / 1e6:.0f} MP limit; "
                       f"downscale it, or raise {MAX_PIXELS_ENV} if it is real")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    check_image(image, str(path))
    return image


def check_declared_pixels(path: str | os.PathLike, data: bytes) -> None:
    """Refuse, before a pixel is decoded, an encoded image (``data``, the file ``path``'s bytes) whose header
    declares more pixels than :func:`max_pixels`, than a JPEG's coded data can hold (:data:`MAX_JPEG_PIXELS_PER_BYTE`;
    header segments such as EXIF or comments do not count), or than the memory free can decode."""
    header = _image_header(data)
    if header is None:
        return
    width, height, pixel_bytes = header
    limit = max_pixels()
    if width * height > limit:
        raise UdhError(f"{path}: the image declares {width}x{height} pixels, over the {limit / 1e6:.0f} MP limit; "
                       f"downscale it, or raise {MAX_PIXELS_ENV} if it is real")
    if data[:2] == b"\xff\xd8" and width * height > jpeg_coded_bytes(data) * MAX_JPEG_PIXELS_PER_BYTE:
        raise UdhError(f"{path}: the JPEG declares {width}x{height} pixels in only {jpeg_coded_bytes(data)} bytes of coded data: "
                       f"it is truncated or damaged; copy the whole file again")
    from udh_cli.budget import check_memory

    # Only what the decode itself holds (the pixels and the file's bytes): a caller making larger copies checks those.
    check_memory(pixel_bytes * width * height + len(data), f"{path}: decoding its {width}x{height} pixels", "downscale the image")


def jpeg_coded_bytes(data: bytes) -> int:
    """The bytes of a JPEG from its first scan on: what its pixels are coded in. Header segments (EXIF, XMP,
    comments) are skipped by their lengths; a header that cannot be walked counts whole."""
    position = 2
    while position + 4 <= len(data) and data[position] == 0xFF:
        marker = data[position + 1]
        if marker == 0xDA:  # start of scan
            return len(data) - position
        if marker == 0xFF:  # fill byte
            position += 1
            continue
        position += 2 + int.from_bytes(data[position + 2:position + 4], "big")
    return len(data)


_STDERR_LOCK = threading.Lock()
# What libjpeg prints when it met damage and went on with invented pixels (grey blocks, a shifted half).
DAMAGE_MESSAGES = ("Corrupt JPEG data", "Premature end of JPEG file", "Invalid JPEG file structure")


@contextlib.contextmanager
def native_messages_silenced(captured: list[str] | None = None, fds: tuple[int, ...] = (2,)):
    """Mute what the C codecs print on stderr while decoding a broken file ("libpng error: ...",
    "Corrupt JPEG data", OpenCV's WARN log): the user gets one clear line from udh instead. The lines printed
    are appended to ``captured`` when it is given. ``fds``: the descriptors muted (OpenCV's FFmpeg log goes to
    stdout, 1, as well)."""
    with _STDERR_LOCK:
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        saved: dict[int, int] = {}
        sink = None
        try:
            sys.stdout.flush()
            sys.stderr.flush()
            try:
                sink = tempfile.TemporaryFile() if captured is not None else open(os.devnull, "wb")  # noqa: SIM115
            except OSError:  # no room for the capture (a full disk): mute at least
                sink = open(os.devnull, "wb")  # noqa: SIM115
            for fd in fds:
                saved[fd] = os.dup(fd)
                os.dup2(sink.fileno(), fd)
        except (OSError, ValueError, AttributeError):  # no such fd or no sys.stderr: only the log is muted
            pass
        try:
            yield
        finally:
            for fd, original in saved.items():
                os.dup2(original, fd)
                os.close(original)
            if sink is not None:
                if captured is not None and sink.seekable():
                    sink.seek(0)
                    captured.extend(sink.read(1 << 16).decode(errors="replace").splitlines())
                sink.close()
            cv2.utils.logging.setLogLevel(level)


def check_image(image: np.ndarray, name: str = "image") -> None:
    """Raise :class:`UdhError` unless ``image`` is a finite 2-D grey or 3-channel array of usable size."""
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3)):
        raise UdhError(f"{name}: expected an (H, W) or (H, W, 3) image array")
    h, w = image.shape[:2]
    if min(h, w) < MIN_IMAGE_SIDE:
        raise UdhError(f"{name}: the image is {w}x{h} pixels; it needs at least {MIN_IMAGE_SIDE} on each side")
    if image.dtype.kind == "f" and not np.all(np.isfinite(image)):
        raise UdhError(f"{name}: the image holds NaN or infinite values")


def scaled_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    """``(width, height)`` times ``scale``, rounded, and never below :data:`MIN_IMAGE_SIDE` on a side.

    Pair it with :func:`udh_cli.geometry.rescale_homography`, which is exact for whatever size this returns.
    """
    return max(MIN_IMAGE_SIDE, round(size[0] * scale)), max(MIN_IMAGE_SIDE, round(size[1] * scale))


def to_gray_float(image: np.ndarray) -> np.ndarray:
    """Any supported image -> (H, W) float32 grey in [0, 1].

    Integers are divided by their type's maximum (255 for 8-bit, 65535 for 16-bit); float input is
    taken to be in [0, 1] already. Colour is assumed BGR, as OpenCV reads it.
    """
    check_image(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    elif image.ndim == 3:
        if image.dtype not in (np.uint8, np.uint16, np.float32):  # depths cvtColor does not take
            image = _unit_float(image)
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return _unit_float(image)


def local_contrast(gray: np.ndarray, sigma: float, floor: float = 0.01) -> np.ndarray:
    """(H, W) float32 -> (H, W) float32 with zero local mean and unit local standard deviation.

    Mean and deviation are Gaussian-weighted over ``sigma`` pixels. This removes illumination that varies
    across the image (shading, vignetting, a lit and a shadowed side), which a single gain and bias cannot
    model. ``floor`` (in the units of ``gray``, [0, 1]) caps the gain in flat regions, so that sensor noise
    there is not amplified into texture.
    """
    mean = cv2.GaussianBlur(gray, (0, 0), sigma)
    detail = gray - mean
    deviation = np.sqrt(cv2.GaussianBlur(detail * detail, (0, 0), sigma))
    return (detail / np.maximum(deviation, floor)).astype(np.float32)


def _unit_float(image: np.ndarray) -> np.ndarray:
    """float32 copy of ``image`` with integer types scaled by their maximum, so full scale is 1."""
    if image.dtype.kind in "iu":
        return image.astype(np.float32) / np.float32(np.iinfo(image.dtype).max)
    return image.astype(np.float32)


def to_gray_u8(image: np.ndarray, stretch: bool = False) -> np.ndarray:
    """Any supported image -> (H, W) uint8 grey, the input that feature detectors want.

    With ``stretch``, the 0.1-99.9 percentile range of the grey values is mapped to 0-255 first. 16-bit
    and float data (thermal, raw) often fill a small part of their range, and 8 bits of it would hold
    too few grey levels for a detector; a constant image stays constant.
    """
    gray = to_gray_float(image)
    if stretch:
        gray = stretch_contrast(gray)
    return np.clip(gray * 255.0 + 0.5, 0, 255).astype(np.uint8)


def stretch_contrast(image: np.ndarray, low: float = 0.1, high: float = 99.9) -> np.ndarray:
    """Map the ``low``-``high`` percentile range of ``image`` (any shape, one range for all channels) to
    [0, 1], as float32. Values outside it go beyond [0, 1]; clip them if needed. Constant input is kept."""
    values = image.astype(np.float32)
    lo, hi = np.percentile(values, (low, high))
    if hi - lo <= 1e-12 * max(1.0, abs(float(hi))):
        return values
    return (values - np.float32(lo)) / np.float32(hi - lo)


def to_bgr_u8(image: np.ndarray) -> np.ndarray:
    """Any supported image -> (H, W, 3) uint8 BGR, for drawing and compositing."""
    gray_or_colour = image
    if image.dtype != np.uint8:
        gray_or_colour = np.clip(_unit_float(image) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if gray_or_colour.ndim == 2 or gray_or_colour.shape[2] == 1:
        return cv2.cvtColor(gray_or_colour, cv2.COLOR_GRAY2BGR)
    return gray_or_colour


def temporary_name(path: Path) -> Path:
    """``.NAME.<64 random bits>.part`` beside ``path``. Not ``mkstemp``: it names the file only once it exists, so an
    interrupt (Ctrl-C, SIGTERM) in between would leave a file nobody knows to remove."""
    return path.parent / f".{path.name}.{secrets.token_hex(8)}.part"


def create_new(path: Path) -> int:
    """Create ``path`` (which must not exist) owner-only, as ``mkstemp`` does; returns its descriptor."""
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o600)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename: a reader never sees a
    half-written file, and an interrupted write leaves the old file (if any). Raises :class:`UdhError` when the
    file cannot be written (read-only or full file system...)."""
    path = check_output_path(path)
    folder = path.parent
    mode = new_file_mode(path)
    tmp = temporary_name(path)
    try:
        try:
            fd = create_new(tmp)
        except OSError as exc:
            raise UdhError(f"{path}: cannot create a file in {folder} ({exc.strerror}); choose another output path") from None
        if hasattr(os, "fchmod"):  # the usual permissions, not owner-only
            os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):  # e.g. the disk filled up: one line for the user, no partial file
            raise UdhError(f"{path}: writing it failed ({exc.strerror}); check the free space and permissions") from None
        raise
    return path


def check_output_path(path: str | os.PathLike, suffixes: tuple[str, ...] | None = None) -> Path:
    """Raise :class:`UdhError` unless a file can be written at ``path``: its folder exists and is writable,
    it is not itself a folder, and (if ``suffixes`` is given) its suffix is one of them. Call it before
    long work, so that a bad output path fails at once rather than after the work is done."""
    path = Path(path)
    folder = path.parent
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise UdhError(f"{path}: unknown file type '{path.suffix}'; use one of {', '.join(suffixes)}")
    try:
        if path.is_dir():
            raise UdhError(f"{path}: is a folder; give a file name")
        if not folder.is_dir():
            raise UdhError(f"{path}: the folder {folder} does not exist; create it first")
        if not os.access(folder, os.W_OK):
            raise UdhError(f"{path}: the folder {folder} is not writable; choose another output path")
    except OSError as exc:  # e.g. a name longer than the file system takes (ENAMETOOLONG)
        raise UdhError(f"{path}: cannot write a file there ({exc.strerror or exc}); choose another output path") from None
    temporary = len(os.fsencode(temporary_name(path).name))  # the name atomic_write_bytes writes first must fit too
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        limit = 255
    if temporary > limit:
        raise UdhError(f"{path}: the name is too long for this file system (with the temporary name it is written under, "
                       f"{temporary} bytes where {limit} are allowed); choose a shorter name")
    return path


def new_file_mode(path: Path) -> int:
    """Permissions for a file written at ``path``: those of the file it replaces, else 0o666 minus umask."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        umask = os.umask(0o022)
        os.umask(umask)
        return 0o666 & ~umask


def encode_image(path: str | os.PathLike, image: np.ndarray) -> bytes:
    """``image`` encoded by the suffix of ``path`` (PNG, JPEG, TIFF...), whose folder is checked for writing."""
    path = check_output_path(path, IMAGE_SUFFIXES)
    suffix = path.suffix.lower()
    messages: list[str] = []
    try:
        # OpenCV's TIFF encoder goes through a temporary file, and libtiff prints its write errors (a full disk).
        with native_messages_silenced(messages):
            ok, encoded = cv2.imencode(suffix, image)
    except cv2.error:
        ok = False
    if not ok:
        said = next((line.strip() for line in messages if line.strip()), "")
        raise UdhError(f"{path}: OpenCV could not encode a {image.shape} {image.dtype} image as {suffix}"
                       + (f" ({said[:120]}); check the free space of the temporary folder" if said else ""))
    return encoded.tobytes()


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Encode ``image`` by the suffix of ``path`` (PNG, JPEG, TIFF...) and write it atomically."""
    return atomic_write_bytes(path, encode_image(path, image))
