"""Live mode: mosaic a folder while a flight is still writing frames into it (``udh mosaic FOLDER --follow``).

The folder is polled. A frame joins once it is complete (a frame being copied or written is never read half-way,
however long its writer pauses): a JPEG or PNG once it ends with its format's end marker and decodes without
damage, a TIFF once every strip or tile its header names lies inside the file; a frame of another format once its
size and modification time are unchanged over two polls and it is at least ``settle_s`` old. After the flight ends,
a JPEG, PNG or TIFF that never became whole joins by that rule too, for the run to refuse by name. Each new frame
is handed at once to ``on_frames`` (the quick look, :mod:`.quicklook`). Every ``refresh_every`` new frames the
mosaic, its preview, sidecar and map files are rewritten from the frames so far. Each refresh is a whole
:func:`~udh_cli.mosaic.run.run_mosaic` run with the pair cache, so only the new frames' pairs (and the loop
closures that changed) are estimated: the solve is redone in full each time, which costs little next to the pairs
(1.3 s for 500 frames). A refresh can run in another process (``start_refresh``), so that new frames are not kept
waiting behind it. The flight is over when a file named ``sentinel`` appears in the folder or no new frame has come
for ``idle_timeout_s``. When the last refresh already held every frame, its mosaic is the final one; otherwise a
last run over every frame makes it, with the folder itself as its source (its pairs come from the cache, so it
costs the solve and the compositing).

Why polling and not inotify: it works the same on every OS and on network shares; at ``poll_s`` 0.1 a scan of a
folder of 1,000 frames costs a few ms, and a frame is seen within a tenth of a second of its last byte.
"""

from __future__ import annotations

import os
import shutil
import time
from concurrent.futures import Future, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.images import DAMAGE_MESSAGES, IMAGE_SUFFIXES, native_messages_silenced, check_declared_pixels
from udh_cli.mosaic.report import Reporter
from udh_cli.processes import remove_dead_runs_folders, run_temp_folder

FOLLOW_STAGING_PREFIX = ".udh-follow-"  # the refreshes' folder of links to the complete frames, beside the output


@dataclass(frozen=True)
class FollowConfig:
    """How a live run follows its folder.

    Attributes:
        refresh_every: rewrite the mosaic after this many new frames.
        poll_s: seconds between looks at the folder.
        settle_s: a frame must be this many seconds old, beside unchanged over two polls, to be read.
        idle_timeout_s: no new frame for this long ends the flight.
        sentinel: a file of this name in the folder ends the flight at once (it is not a frame).
    """

    refresh_every: int = 5
    poll_s: float = 0.1
    settle_s: float = 1.0
    idle_timeout_s: float = 60.0
    sentinel: str = "DONE"


@dataclass
class _Watch:
    """What the poller has seen: file -> (size, mtime) at the last poll, and the frames that are complete."""

    seen: dict[Path, tuple[int, float]] = field(default_factory=dict)
    complete: list[Path] = field(default_factory=list)
    not_whole: dict[Path, tuple[int, float]] = field(default_factory=dict)  # settled frames that did not decode whole, as then


# The last bytes of a complete file: JPEG's end-of-image marker, PNG's IEND chunk.
END_MARKERS = {".jpg": b"\xff\xd9", ".jpeg": b"\xff\xd9", ".png": b"IEND\xaeB`\x82"}
# Where a TIFF's pixels lie: the tags of its strips' (or tiles') offsets and byte counts.
TIFF_OFFSETS, TIFF_BYTE_COUNTS = (273, 324), (279, 325)


def structurally_whole(path: Path, size: int) -> bool | None:
    """Whether the frame ``path`` (``size`` bytes) is whole by its format's structure (:func:`ends_whole`,
    :func:`tiff_whole`); None for a format without such a check."""
    suffix = path.suffix.lower()
    if suffix in END_MARKERS:
        return ends_whole(path, size)
    if suffix in (".tif", ".tiff"):
        return tiff_whole(path, size)
    return None


def tiff_whole(path: Path, size: int) -> bool:
    """Whether the TIFF ``path`` (``size`` bytes) holds its first image whole: its header and directory read, and
    every strip or tile they name ends inside the file. Pillow reads only the header here; a TIFF whose header it
    cannot read counts as not yet whole, so it joins when the flight ends (a half-written header looks the same)."""
    import warnings

    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a half-written directory: Pillow's warnings say what the answer does
            with Image.open(path) as image:
                tags = image.tag_v2
                offsets = next((tags[tag] for tag in TIFF_OFFSETS if tags.get(tag)), None)
                counts = next((tags[tag] for tag in TIFF_BYTE_COUNTS if tags.get(tag)), None)
    except Exception:  # noqa: BLE001 - a header Pillow cannot read yet is a file not yet whole
        return False
    if not offsets or not counts or len(offsets) != len(counts):
        return False
    return max(int(offset) + int(count) for offset, count in zip(offsets, counts)) <= size


def ends_whole(path: Path, size: int) -> bool:
    """Whether ``path`` (``size`` bytes) ends with its format's end marker and decodes: complete, whatever its age.

    The decode matters because a JPEG's EXIF thumbnail ends with the same marker as the image: a copy cut just
    after it would otherwise pass. It decodes at an eighth of the size (JPEG's DCT scaling), a few ms."""
    marker = END_MARKERS.get(path.suffix.lower())
    if marker is None or size < 64:
        return False
    try:
        with path.open("rb") as handle:
            handle.seek(-len(marker), os.SEEK_END)
            if handle.read() != marker:
                return False
    except OSError:
        return False
    return decodes_whole(path, size)


def decodes_whole(path: Path, size: int) -> bool:
    """Whether the JPEG or PNG ``path`` (``size`` bytes) decodes, at an eighth of its size, without the decoder
    saying it ended early or is damaged; one whose header declares too many pixels counts as whole here, never
    decoded (the run's reader refuses it, saying why). Why beside :func:`ends_whole`: bytes after the end marker
    (zero padding, a motion photo's trailer) leave a whole frame that does not end with it."""
    try:
        with path.open("rb") as handle:
            data = handle.read(size)
    except OSError:
        return False
    if len(data) != size:
        return False
    try:
        check_declared_pixels(path, data)
    except UdhError:
        return True  # whole as far as its end marker says; never decoded here: the run's reader refuses it, saying why
    messages: list[str] = []
    with native_messages_silenced(messages):  # a JPEG cut after its thumbnail decodes, but says it ended early
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
    damaged = any(line.lstrip().startswith(DAMAGE_MESSAGES) for line in messages)
    return decoded is not None and decoded.size > 0 and not damaged


def poll_complete_frames(folder: Path, watch: _Watch, settle_s: float, exclude: set[Path], now: float,
                         flight_over: bool = False) -> list[Path]:
    """Look at ``folder`` once; the frames that became complete since the last look, in name order. With
    ``flight_over``, a frame that settled joins even when its structure says it is not whole (it is damaged)."""
    current: dict[Path, tuple[int, float]] = {}
    for entry in os.scandir(folder):
        path = Path(entry.path)
        if not entry.is_file() or path.suffix.lower() not in IMAGE_SUFFIXES or path.name.startswith(".") or path.resolve() in exclude:
            continue
        stat = entry.stat()
        current[path] = (stat.st_size, stat.st_mtime)
    done = set(watch.complete)
    new = []
    for path, state in current.items():
        if path in done or state[0] == 0:
            continue
        settled = watch.seen.get(path) == state and now - state[1] >= settle_s
        if _complete(path, state[0], settled, flight_over, watch.not_whole.get(path) == state):
            new.append(path)
        elif settled:
            watch.not_whole[path] = state  # not decoded again until it changes
    watch.seen = current
    new.sort(key=lambda p: p.name)
    watch.complete.extend(new)
    return new


def _complete(path: Path, size: int, settled: bool, flight_over: bool, known_not_whole: bool = False) -> bool:
    """Whether a frame may be read: whole by its structure; else, once ``settled`` (unchanged over two polls and
    old enough), a format without such a structure, a JPEG or PNG that decodes whole with bytes after its end
    marker, or any frame after the flight. ``known_not_whole``: settled and judged not whole as it is now."""
    if known_not_whole:
        return flight_over
    whole = structurally_whole(path, size)
    if whole is None:
        return settled
    if not whole and settled and path.suffix.lower() in END_MARKERS:
        whole = decodes_whole(path, size)
    return whole or (flight_over and settled)


def check_followed_folder(folder: Path) -> None:
    """Refuse a source that is not a folder (a video, a typo) before anything is loaded."""
    if not Path(folder).is_dir():
        raise UdhError(f"--follow {folder}: not a folder; live mode watches a folder that frames are written into")


def follow_mosaic(folder: str | Path, output: str | Path, run: Callable[..., dict[str, Any]], follow: FollowConfig = FollowConfig(),
                  reporter: Reporter | None = None, exclude: Callable[[], set[Path]] = frozenset, clock: Callable[[], float] = time.time,
                  sleep: Callable[[float], None] = time.sleep, on_frames: Callable[[list[Path]], None] | None = None,
                  start_refresh: Callable[[Path], Future] | None = None) -> dict[str, Any]:
    """Follow ``folder`` until the flight ends; returns the final run's sidecar.

    ``run(source, live=None)`` mosaics a folder of frames into ``output`` (``run_mosaic`` with the pair cache on);
    refreshes give it a staging folder of links to the complete frames, the final run ``folder`` itself and
    ``live``, the record of the flight that its sidecar carries. When the last refresh held every frame, its
    report is returned instead, with ``live`` added but not written (:func:`~.run.run_live` writes it).
    ``exclude()`` names the files (resolved paths) that are never frames: the run's own outputs, asked anew at
    every poll because a split run adds part files. ``on_frames(paths)`` gets the frames as they become
    complete. ``start_refresh(source)``, when given, starts a refresh elsewhere and returns its future: the next
    refresh waits for it, new frames do not, and the final run comes after it.
    """
    reporter = reporter or Reporter(quiet=True)
    folder, output = Path(folder), Path(output)
    check_followed_folder(folder)
    if follow.refresh_every < 1 or follow.poll_s <= 0 or follow.idle_timeout_s <= 0 or follow.settle_s < 0:
        raise UdhError("--follow: the refresh interval (frames), the poll interval and the idle timeout must be positive")
    watch = _Watch()
    refreshed_at, last_new, refreshes = 0, clock(), 0
    pending: Future | None = None
    latest: dict[str, Any] | None = None  # the last refresh that was written
    for gone in remove_dead_runs_folders(output.parent, FOLLOW_STAGING_PREFIX):
        reporter.info(f"live: removed {gone.name}, left by a live run that was killed")
    staging = run_temp_folder(output.parent, FOLLOW_STAGING_PREFIX)

    def refreshed(outcome: Callable[[], dict[str, Any]], frames: int) -> None:
        nonlocal refreshes, start_refresh, latest
        try:
            report = outcome()
        except UdhError as exc:  # a refresh that cannot be written (a canvas too large...) must not end the flight
            reporter.warn(f"live: the mosaic of {frames} frames was not refreshed: {exc}")
        except BrokenProcessPool:  # the refresh process died (killed, out of memory): refresh here from now on
            start_refresh = None
            reporter.warn(f"live: the refresh process stopped while refreshing {frames} frames; later refreshes run in this process")
        except Exception as exc:  # noqa: BLE001 - a refresh is a convenience: only the final run may end the flight
            reporter.warn(f"live: the mosaic of {frames} frames was not refreshed ({type(exc).__name__}: {exc})")
        else:
            refreshes += 1
            latest = report
            reporter.info(f"live: mosaic refreshed with {report['summary']['placed']} of {report['summary']['frames']} frames placed")

    try:
        while True:
            now = clock()
            new = poll_complete_frames(folder, watch, follow.settle_s, exclude(), now)
            if new:
                last_new = now
                for path in new:
                    _link(path, staging / path.name)
                reporter.info(f"live: {len(watch.complete)} frames ({', '.join(p.name for p in new[:3])}{' ...' if len(new) > 3 else ''})")
                if on_frames is not None:
                    on_frames(new)
            if pending is not None and pending.done():
                refreshed(pending.result, refreshed_at)
                pending = None
            ended = (folder / follow.sentinel).exists() or now - last_new >= follow.idle_timeout_s
            due = len(watch.complete) >= 2 and len(watch.complete) - refreshed_at >= follow.refresh_every
            if due and not ended and pending is None:
                refreshed_at = len(watch.complete)
                if start_refresh is None:
                    refreshed(lambda: run(staging), refreshed_at)
                else:
                    pending = start_refresh(staging)
            if ended:
                break
            sleep(follow.poll_s)
        if pending is not None:  # the final run writes the same files: the refresh under way finishes first
            refreshed(pending.result, refreshed_at)
            pending = None
        _wait_until_settled(folder, watch, follow, exclude, clock, sleep)
        if len(watch.complete) < 2:
            raise UdhError(f"--follow {folder}: the flight ended with {len(watch.complete)} complete frame(s); a mosaic needs two")
        ended_by = "sentinel" if (folder / follow.sentinel).exists() else "idle timeout"
        cause = f"a {follow.sentinel} file" if ended_by == "sentinel" else f"no new frame for {follow.idle_timeout_s:g} s"
        why = f"live: the flight ended ({cause}) with {len(watch.complete)} frames"
        live = {"refreshes": refreshes, "frames": len(watch.complete), "ended_by": ended_by}
        if latest is not None and latest["summary"]["frames"] == len(watch.complete):  # the staging folder holds complete frames only
            reporter.info(f"{why}; the last refresh held all of them, so its mosaic is the final one")
            latest["live"] = {**live, "final": "the last refresh"}
            return latest
        reporter.info(f"{why}; making the final mosaic of all of them (the pairs already estimated are reused)")
        record = {**live, "final": "a final run"}
        report = run(folder, live=record)
        report["live"] = record  # in its sidecar already, where ``run`` is run_mosaic
        return report
    finally:
        if pending is not None and not pending.cancel():  # a refresh still reads the staging folder: let it end
            wait([pending])
        shutil.rmtree(staging, ignore_errors=True)


def _wait_until_settled(folder: Path, watch: _Watch, follow: FollowConfig, exclude: Callable[[], set[Path]], clock, sleep) -> None:
    """After the end: the frames still being written are waited for (up to the idle timeout), so that the
    final run reads every frame whole."""
    deadline = clock() + follow.idle_timeout_s
    while clock() < deadline:
        poll_complete_frames(folder, watch, follow.settle_s, exclude(), clock(), flight_over=True)
        if set(watch.seen) <= set(watch.complete):
            return
        sleep(follow.poll_s)


def _link(source: Path, target: Path) -> None:
    """A symbolic link where the system allows it (no copy of the frame), else a copy."""
    try:
        target.symlink_to(source.resolve())
    except OSError:
        shutil.copy2(source, target)
