"""Mosaic input: a folder of frames or a video, read once into small grey working copies.

Full-resolution pixels are kept only for the first frames, within a budget the caller gives, until the rendering
takes them; compositing reads the others again one at a time (:meth:`FrameSet.full_images`).
"""

from __future__ import annotations

import os
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.images import IMAGE_SUFFIXES, native_messages_silenced, read_image, scaled_size, to_gray_float, to_gray_u8
from udh_cli.mosaic.inputs.display import display_u8, flight_value_range, to_display
from udh_cli.mosaic.inputs.lens import Lens
from udh_cli.mosaic.inputs.listing import natural_key, not_a_file, subfolder_hint
from udh_cli.mosaic.inputs.metadata import FrameMetadata, read_metadata
from udh_cli.mosaic.outputs.staging import earlier_outputs
from udh_cli.mosaic.report import Reporter

ORDERS = ("name", "time")  # the --order choices
# Files a frame folder may hold that are not frames: the simulator's ground truth, and live mode's end-of-flight
# sentinel (FollowConfig.sentinel), which stays in the folder its final run reads.
IGNORED_FILES = ("ground_truth.json", "DONE")


@dataclass
class Frame:
    """One input frame.

    Attributes:
        index: position in the sequence, 0-based; pairs and the sidecar refer to frames by it.
        name: the file name, or ``"video.mp4#120"`` for frame 120 of a video.
        size: (width, height) at full resolution, after EXIF orientation.
        work: (h', w') uint8 grey copy at the working size (the longest side at most ``work_size``).
        path: the image file; ``None`` for video frames.
        video_frame: the frame number in the video; ``None`` for image files.
        capture_time: EXIF capture time, when ordering by time.
        metadata: what the file's EXIF and XMP say (GPS, camera, DJI flight data); None for video frames.
        stamp: the file's :func:`file_stamp` when it was read for the working copy; None for video frames.
    """

    index: int
    name: str
    size: tuple[int, int]
    work: np.ndarray
    path: Path | None = None
    video_frame: int | None = None
    capture_time: str | None = None
    metadata: FrameMetadata | None = None
    stamp: tuple[int, int, int] | None = None

    @property
    def work_size(self) -> tuple[int, int]:
        return (self.work.shape[1], self.work.shape[0])


@dataclass
class FrameSet:
    """The frames of one run, in sequence order, and the files that were skipped (with why)."""

    source: Path
    frames: list[Frame]
    skipped: list[dict] = field(default_factory=list)  # {"file": name, "reason": text}
    # For 16-bit or float frames: the flight-wide (low, high) grey range, in units where the type's maximum
    # is 1, that maps to 0-255 in the work copies and the mosaic. None for 8-bit frames, used as they are.
    value_range: tuple[float, float] | None = None
    lens: Lens | None = None  # every frame is undistorted by it as it is read (:mod:`.lens`)
    lens_fit: dict | None = None  # how the lens was estimated from the flight (``--camera estimate``, :mod:`.lens_fit`)
    source_stamp: tuple[int, int, int] | None = None  # a video's :func:`file_stamp` when its frames were read
    # Full-resolution frames decoded while reading (the first ones, up to open_frames' budget), undistorted, until
    # the rendering takes them (take_decoded): a frame so kept is decoded once for the whole run.
    decoded_while_reading: dict[int, np.ndarray] = field(default_factory=dict, repr=False)

    @property
    def is_video(self) -> bool:
        return bool(self.frames) and self.frames[0].video_frame is not None

    def take_decoded(self, indices: Iterable[int]) -> dict[int, np.ndarray]:
        """The frames of ``indices`` decoded while reading, as :meth:`full_images` gives them ((H, W, 3) BGR uint8),
        handed over: the set no longer holds them. A file changed on disk since is refused, as there."""
        taken = {}
        for index in sorted(set(indices) & set(self.decoded_while_reading)):
            if not self.is_video:
                _check_unchanged(self.frames[index].path, self.frames[index].stamp)
            image = self.decoded_while_reading.pop(index)
            taken[index] = image if self.is_video else display_u8(image, self.value_range)
        if self.is_video and taken:
            _check_unchanged(self.source, self.source_stamp)
        return taken

    def decoded_bytes(self) -> int:
        """Bytes of the frames still held from reading (:attr:`decoded_while_reading`)."""
        return sum(image.nbytes for image in self.decoded_while_reading.values())

    def drop_decoded(self, keep: Iterable[int]) -> None:
        """Let go of the frames decoded while reading but those of ``keep`` (e.g. the frames no part renders)."""
        keep = set(keep)
        self.decoded_while_reading = {i: image for i, image in self.decoded_while_reading.items() if i in keep}

    def full_images(self, indices: Iterable[int]) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(index, (H, W, 3) BGR uint8)`` at full resolution for ``indices``, in sequence order.

        Image files are read again; a video is decoded again from the start, sequentially. A file changed on disk
        since its working copy was read is refused (:class:`UdhError`): its homography is the old picture's.
        """
        wanted = sorted(set(indices))
        if not self.is_video:
            for index in wanted:
                frame = self.frames[index]
                _check_unchanged(frame.path, frame.stamp)
                yield index, display_u8(_undistorted(read_image(frame.path), self.lens), self.value_range)
            return
        _check_unchanged(self.source, self.source_stamp)
        by_video_frame = {self.frames[i].video_frame: i for i in wanted}
        capture = _open_capture(self.source)
        try:
            number, last = 0, max(by_video_frame)
            while number <= last:
                ok, image, _ = read_video_frame(capture)  # a frame kept on the first pass decoded cleanly then
                if not ok:
                    raise UdhError(f"{self.source}: the video ended early on the second pass (frame {number}); extract its frames to a folder")
                if number in by_video_frame:
                    yield by_video_frame[number], _undistorted(image, self.lens)
                number += 1
        finally:
            capture.release()


def file_stamp(path: Path) -> tuple[int, int, int] | None:
    """``(size in bytes, modification time in ns, inode)`` of ``path``: any of them changes when a file is
    rewritten or replaced. None when it cannot be read."""
    try:
        info = os.stat(path)
    except OSError:
        return None
    return info.st_size, info.st_mtime_ns, info.st_ino


def _check_unchanged(path: Path, stamp: tuple[int, int, int] | None) -> None:
    """Refuse a file that changed since ``stamp`` was taken (None: nothing was recorded, nothing to compare)."""
    if stamp is not None and file_stamp(path) != stamp:
        raise UdhError(f"{path}: changed on disk while the mosaic was made (its pairs were estimated from the earlier file); "
                       f"run again once the frames stay as they are (--resume reuses the pairs of the others)")


def _undistorted(image: np.ndarray, lens: Lens | None) -> np.ndarray:
    return image if lens is None else lens.undistort(image)


def work_copy(image: np.ndarray, work_size: int) -> np.ndarray:
    """(h', w') grey copy whose longest side is at most ``work_size`` pixels (never enlarged): uint8 for
    8-bit frames, float32 in [0, 1] of the type's range otherwise (see :func:`stretch_work_copies`)."""
    grey = to_gray_u8(image) if image.dtype == np.uint8 else to_gray_float(image)
    h, w = grey.shape
    scale = min(1.0, work_size / max(w, h))
    if scale >= 1.0:
        return grey
    return cv2.resize(grey, scaled_size((w, h), scale), interpolation=cv2.INTER_AREA)


def stretch_work_copies(frames: list[Frame]) -> tuple[float, float] | None:
    """Turn float work copies (16-bit or float frames) into uint8 with one flight-wide range; returns the
    range, or None when every frame is 8-bit already."""
    floats = [f for f in frames if f.work.dtype != np.uint8]
    if not floats:
        return None
    value_range = flight_value_range([f.work for f in floats])
    for frame in floats:
        frame.work = to_display(frame.work, value_range)
    return value_range


def open_frames(
    source: str | Path,
    work_size: int,
    order: str = "name",
    every: int = 1,
    exclude: Iterable[Path] = (),
    reporter: Reporter | None = None,
    lens: Lens | None = None,
    keep_decoded_bytes: int = 0,
) -> FrameSet:
    """Read a folder of frames or a video into a :class:`FrameSet`.

    Args:
        source: a folder of JPEG/PNG/TIFF frames, or a video file.
        work_size: longest side of the working copies, pixels.
        order: ``"name"`` (natural sort of file names) or ``"time"`` (EXIF capture time, then name).
        every: for a video, keep every N-th frame.
        exclude: files to leave out (the run's own outputs, when they are written into the folder).
        lens: a camera model: every frame is undistorted by it as it is read (:mod:`.lens`); frames of another
            shape than its calibration are refused.
        keep_decoded_bytes: keep the first frames' full-resolution decodes up to this many bytes, for the
            rendering to take (:meth:`FrameSet.take_decoded`) instead of decoding them again; 0: keep none.

    Corrupt frames and non-image files are skipped with a warning and listed in ``skipped``.
    Raises :class:`UdhError` when fewer than two usable frames remain or the video cannot be decoded.
    """
    reporter = reporter or Reporter(quiet=True)
    source = Path(source)
    if order not in ORDERS:
        raise UdhError(f"unknown order '{order}'; choose one of: {', '.join(ORDERS)}")
    if every < 1:
        raise UdhError(f"--every {every}: give a positive number of frames")
    if not source.exists():
        raise UdhError(f"{source}: no such folder or video; check the path")
    kept = _DecodeKeeper(keep_decoded_bytes)
    frames = (_open_video(source, work_size, every, reporter, lens, kept) if source.is_file()
              else _open_folder(source, work_size, order, exclude, reporter, lens, kept))
    _check_sizes(frames, reporter)
    frames.lens = lens
    return frames


def frames_listed(source: Path, every: int = 1) -> int:
    """About how many frames :func:`open_frames` will read, known before reading them: a folder's image files, or
    a video's frame count over ``every`` (0 when the file does not say)."""
    if source.is_dir():
        try:
            return sum(1 for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
        except OSError:  # reading the folder says why, in one line
            return 0
    capture = _open_capture(source)
    try:
        return int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0) // max(1, every)
    finally:
        capture.release()


class _DecodeKeeper:
    """Full-resolution decodes kept while reading, the first ones up to ``budget_bytes``."""

    def __init__(self, budget_bytes: int) -> None:
        self.budget_bytes, self.kept, self.kept_bytes, self.full = budget_bytes, {}, 0, budget_bytes <= 0

    def offer(self, index: int, image: np.ndarray) -> None:
        if not self.full and self.kept_bytes + image.nbytes <= self.budget_bytes:
            self.kept[index] = image
            self.kept_bytes += image.nbytes
        else:  # the first frame over the budget closes it: the kept frames stay the first ones, as the rendering reads them
            self.full = True


def _open_folder(folder: Path, work_size: int, order: str, exclude: Iterable[Path], reporter: Reporter, lens: Lens | None,
                 kept: _DecodeKeeper | None = None) -> FrameSet:
    kept = kept or _DecodeKeeper(0)
    excluded = {Path(p).resolve() for p in exclude}
    try:
        listing = list(folder.iterdir())
    except OSError as exc:
        raise UdhError(f"{folder}: cannot list the folder ({exc.strerror}); check its permissions") from None
    skipped: list[dict] = []
    entries = []
    for path in sorted((p for p in listing if not p.name.startswith(".") and p.name not in IGNORED_FILES), key=lambda p: natural_key(p.name)):
        why = not_a_file(path)
        if why is None:
            entries.append(path)
        elif why:  # a frame that cannot be read must be named, never dropped without a word (a FIFO is never opened)
            skipped.append({"file": path.name, "reason": why})
            reporter.warn(f"skipping {path.name}: {why}")
    entries = [p for p in entries if p.resolve() not in excluded]
    candidates = []
    earlier = earlier_outputs(entries)
    for path in entries:
        if path in earlier:
            skipped.append({"file": path.name, "reason": f"an earlier udh mosaic's output (its sidecar: {earlier[path]})"})
            reporter.warn(f"skipping {path.name}: an earlier udh mosaic's output ({earlier[path]})")
        elif path.suffix.lower() in IMAGE_SUFFIXES:
            candidates.append(path)
        else:
            skipped.append({"file": path.name, "reason": f"not an image file (suffix '{path.suffix}')"})
            reporter.warn(f"skipping {path.name}: not an image file")
    if not candidates:
        raise UdhError(f"{folder}: no image files found (looked for {', '.join(IMAGE_SUFFIXES)}); point to a folder of frames or a video{subfolder_hint(folder)}")
    metadata = {p: read_metadata(p) for p in candidates}  # headers only: GPS and time for the sidecar and the order
    if order == "time":
        times = {p: metadata[p].capture_time for p in candidates}
        missing = [p.name for p in candidates if times[p] is None]
        if missing:
            reporter.warn(f"{len(missing)} frames have no EXIF capture time and go last, by name: {', '.join(missing[:5])}{'...' if len(missing) > 5 else ''}")
        candidates.sort(key=lambda p: (times[p] is None, times[p] or "", natural_key(p.name)))
    frames: list[Frame] = []
    with reporter.stage("reading frames", len(candidates)) as advance:
        for path in candidates:
            stamp = file_stamp(path)  # before the read: a change during it is a change too
            try:
                image = read_image(path)
            except UdhError as exc:
                skipped.append({"file": path.name, "reason": str(exc)})
                # The reason read_image gives: unreadable (permissions), NaN pixels, not an image...
                reporter.warn(f"skipping {path.name}: cannot be decoded ({str(exc).removeprefix(f'{path}: ')})")
                advance(1)
                continue
            if lens is not None:
                lens.check((image.shape[1], image.shape[0]), path.name)
            image = _undistorted(image, lens)
            kept.offer(len(frames), image)
            frames.append(Frame(len(frames), path.name, (image.shape[1], image.shape[0]), work_copy(image, work_size), path, None,
                                metadata[path].capture_time if order == "time" else None, metadata[path], stamp))
            advance(1)
    if len(frames) < 2:
        found = "no readable image" if not frames else f"only one readable image ({frames[0].name})"
        raise UdhError(f"{folder}: {found}; a mosaic needs at least two overlapping frames{subfolder_hint(folder)}")
    return FrameSet(folder, frames, skipped, stretch_work_copies(frames), decoded_while_reading=kept.kept)


def _open_capture(path: Path) -> cv2.VideoCapture:
    """``cv2.VideoCapture(path)`` without FFmpeg's own lines on stderr ("moov atom not found"...): udh says
    what is wrong in one line. FFmpeg keeps its errors for the decoding that follows, where the process has not
    chosen a log level (OPENCV_FFMPEG_LOGLEVEL is read when the first video is opened): :func:`read_video_frame`
    takes them as the decoder's damage reports. One decoding thread, so that a report comes with its own frame."""
    if "OPENCV_FFMPEG_LOGLEVEL" not in os.environ and "OPENCV_FFMPEG_DEBUG" not in os.environ:
        os.environ["OPENCV_FFMPEG_LOGLEVEL"] = "16"  # AV_LOG_ERROR: damaged packets, nothing chattier
    with native_messages_silenced(fds=(1, 2)):
        capture = cv2.VideoCapture(str(path), cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, 1])
        capture.isOpened()  # FFmpeg probes the file while opening; its complaints are muted with it
    return capture


def read_video_frame(capture: cv2.VideoCapture) -> tuple[bool, np.ndarray | None, str | None]:
    """``capture.read()``, and what the decoder reported while decoding that frame (its first line), else None.

    Why: FFmpeg conceals a damaged packet (the smeared block a mosaic would draw) and says so only in its log;
    its lines are caught here, off the terminal, as the frame's damage."""
    messages: list[str] = []
    with native_messages_silenced(messages, fds=(1, 2)):
        ok, image = capture.read()
    # Only FFmpeg's own lines: a progress bar redrawn meanwhile by another thread is caught too, and is no damage.
    reported = [" ".join(line[match.end():].split()) for line in messages if (match := _FFMPEG_LINE.match(line))]
    return ok, image, (reported[0][:160] if reported else None)


# A line of FFmpeg's log: "[OPENCV:FFMPEG:16] ..." through OpenCV's callback, "[h264 @ 0x55d0...] ..." through its own.
_FFMPEG_LINE = re.compile(r"\s*\[(?:OPENCV:FFMPEG:\d+|[\w,\-]+ @ 0x[0-9a-fA-F]+)\]")


def _open_video(path: Path, work_size: int, every: int, reporter: Reporter, lens: Lens | None, kept: _DecodeKeeper | None = None) -> FrameSet:
    kept = kept or _DecodeKeeper(0)
    if path.suffix.lower() in IMAGE_SUFFIXES:
        raise UdhError(f"{path}: is a single image; give a folder of frames or a video")
    stamp = file_stamp(path)
    capture = _open_capture(path)
    if not capture.isOpened():
        raise UdhError(f"{path}: cannot open this as a video; give a folder of frames or a video OpenCV can decode (e.g. MP4/H.264)")
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or None
    frames: list[Frame] = []
    skipped: list[dict] = []
    try:
        with reporter.stage("reading video", total) as advance:
            number = 0
            damaged_dropped: str | None = None  # a frame --every dropped was damaged: the next kept one is decoded from it
            while True:
                ok, image, damage = read_video_frame(capture)
                if not ok:
                    break
                if number % every != 0:
                    if damage is not None and damaged_dropped is None:
                        damaged_dropped = f"decoded from the damaged #{number} (the decoder says: {damage})"
                elif damage is not None or damaged_dropped is not None:
                    reason = f"damaged (the decoder says: {damage})" if damage is not None else damaged_dropped
                    skipped.append({"file": f"{path.name}#{number}", "reason": reason})
                    reporter.warn(f"skipping {path.name}#{number}: {reason}")
                    damaged_dropped = None
                else:
                    if lens is not None:
                        lens.check((image.shape[1], image.shape[0]), f"{path.name}#{number}")
                    image = _undistorted(image, lens)
                    kept.offer(len(frames), image)
                    frames.append(Frame(len(frames), f"{path.name}#{number}", (image.shape[1], image.shape[0]),
                                        work_copy(image, work_size), None, number))
                number += 1
                advance(1)
    finally:
        capture.release()
    if number == 0:
        raise UdhError(f"{path}: no frame could be decoded from this video; check the file or extract its frames to a folder")
    if total is not None and number < total:
        reporter.warn(f"{path.name}: the decoder stopped after {number} of the {total} frames the video lists; it is damaged or cut short")
    if len(frames) < 2:
        raise UdhError(f"{path}: only {len(frames)} frame kept of {number} (--every {every}); a mosaic needs at least two")
    return FrameSet(path, frames, skipped, stretch_work_copies(frames), source_stamp=stamp, decoded_while_reading=kept.kept)


def _check_sizes(frames: FrameSet, reporter: Reporter) -> None:
    """Mixed sizes are handled (every homography is per frame), but they usually mean a stray file: say so."""
    sizes = Counter(f.size for f in frames.frames)
    if len(sizes) > 1:
        listing = ", ".join(f"{w}x{h} ({n})" for (w, h), n in sizes.most_common())
        reporter.warn(f"the frames come in {len(sizes)} sizes: {listing}; each frame is used at its own size")


def gps_fixes(frames: Sequence[Frame]) -> dict[int, tuple[float, float]]:
    """Frame index -> (latitude, longitude) of every frame whose EXIF carries GPS."""
    return {f.index: (f.metadata.latitude, f.metadata.longitude) for f in frames if f.metadata is not None and f.metadata.has_gps}
