"""Live mode: mosaic a folder while a flight is still writing frames into it (``udh mosaic FOLDER --follow``).

The folder is polled. A frame joins once it is complete: its size and modification time unchanged over two
polls, and at least ``settle_s`` old (a frame being copied or written is never read half-way). Every
``refresh_every`` new frames the mosaic, its preview, sidecar and map files are rewritten from the frames so
far. Each refresh is a whole :func:`~udh_cli.mosaic.pipeline.run_mosaic` run with the pair cache, so only the
new frames' pairs (and the loop closures that changed) are estimated: the solve is redone in full each time,
which costs little next to the pairs (1.3 s for 500 frames). The flight is over when a file named
``sentinel`` appears in the folder or no new frame has come for ``idle_timeout_s``; a last run over every
frame then makes the final mosaic, with the folder itself as its source.

Why polling and not inotify: it works the same on every OS and on network shares, and a drone's frame rate
(one every one to three seconds) needs nothing faster.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from udh_cli.errors import UdhError
from udh_cli.images import IMAGE_SUFFIXES
from udh_cli.mosaic.report import Reporter


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
    poll_s: float = 2.0
    settle_s: float = 1.0
    idle_timeout_s: float = 60.0
    sentinel: str = "DONE"


@dataclass
class _Watch:
    """What the poller has seen: file -> (size, mtime) at the last poll, and the frames that are complete."""

    seen: dict[Path, tuple[int, float]] = field(default_factory=dict)
    complete: list[Path] = field(default_factory=list)


def poll_complete_frames(folder: Path, watch: _Watch, settle_s: float, exclude: set[Path], now: float) -> list[Path]:
    """Look at ``folder`` once; the frames that became complete since the last look, in name order."""
    current: dict[Path, tuple[int, float]] = {}
    for entry in os.scandir(folder):
        path = Path(entry.path)
        if not entry.is_file() or path.suffix.lower() not in IMAGE_SUFFIXES or path.name.startswith(".") or path.resolve() in exclude:
            continue
        stat = entry.stat()
        current[path] = (stat.st_size, stat.st_mtime)
    done = set(watch.complete)
    new = [path for path, state in current.items()
           if path not in done and state[0] > 0 and watch.seen.get(path) == state and now - state[1] >= settle_s]
    watch.seen = current
    new.sort(key=lambda p: p.name)
    watch.complete.extend(new)
    return new


def follow_mosaic(folder: str | Path, output: str | Path, run: Callable[[Path], dict[str, Any]], follow: FollowConfig = FollowConfig(),
                  reporter: Reporter | None = None, exclude: Callable[[], set[Path]] = frozenset, clock: Callable[[], float] = time.time,
                  sleep: Callable[[float], None] = time.sleep) -> dict[str, Any]:
    """Follow ``folder`` until the flight ends; returns the final run's sidecar.

    ``run(source)`` mosaics a folder of frames into ``output`` (``run_mosaic`` with the pair cache on);
    refreshes give it a staging folder of links to the complete frames, the final run ``folder`` itself.
    ``exclude()`` names the files (resolved paths) that are never frames: the run's own outputs, asked anew at
    every poll because a split run adds part files.
    """
    reporter = reporter or Reporter(quiet=True)
    folder, output = Path(folder), Path(output)
    if not folder.is_dir():
        raise UdhError(f"--follow {folder}: not a folder; live mode watches a folder that frames are written into")
    if follow.refresh_every < 1 or follow.poll_s <= 0 or follow.idle_timeout_s <= 0 or follow.settle_s < 0:
        raise UdhError("--follow: the refresh interval (frames), the poll interval and the idle timeout must be positive")
    watch = _Watch()
    refreshed_at, last_new, refreshes = 0, clock(), 0
    staging = Path(tempfile.mkdtemp(prefix=".udh-follow-", dir=output.parent))
    try:
        while True:
            now = clock()
            new = poll_complete_frames(folder, watch, follow.settle_s, exclude(), now)
            if new:
                last_new = now
                for path in new:
                    _link(path, staging / path.name)
                reporter.info(f"live: {len(watch.complete)} frames ({', '.join(p.name for p in new[:3])}{' ...' if len(new) > 3 else ''})")
            ended = (folder / follow.sentinel).exists() or now - last_new >= follow.idle_timeout_s
            if len(watch.complete) >= 2 and len(watch.complete) - refreshed_at >= follow.refresh_every and not ended:
                refreshed_at = len(watch.complete)
                try:
                    report = run(staging)
                except UdhError as exc:  # a refresh that cannot be written (a canvas too large...) must not end the flight
                    reporter.warn(f"live: the mosaic of {refreshed_at} frames was not refreshed: {exc}")
                else:
                    refreshes += 1
                    reporter.info(f"live: mosaic refreshed with {report['summary']['placed']} of {report['summary']['frames']} frames placed")
            if ended:
                break
            sleep(follow.poll_s)
        _wait_until_settled(folder, watch, follow, exclude, clock, sleep)
        if len(watch.complete) < 2:
            raise UdhError(f"--follow {folder}: the flight ended with {len(watch.complete)} complete frame(s); a mosaic needs two")
        report = run(folder)
        report["live"] = {"refreshes": refreshes, "frames": len(watch.complete),
                          "ended_by": "sentinel" if (folder / follow.sentinel).exists() else "idle timeout"}
        return report
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _wait_until_settled(folder: Path, watch: _Watch, follow: FollowConfig, exclude: Callable[[], set[Path]], clock, sleep) -> None:
    """After the end: the frames still being written are waited for (up to the idle timeout), so that the
    final run reads every frame whole."""
    deadline = clock() + follow.idle_timeout_s
    while clock() < deadline:
        poll_complete_frames(folder, watch, follow.settle_s, exclude(), clock())
        if set(watch.seen) <= set(watch.complete):
            return
        sleep(follow.poll_s)


def _link(source: Path, target: Path) -> None:
    """A symbolic link where the system allows it (no copy of the frame), else a copy."""
    try:
        target.symlink_to(source.resolve())
    except OSError:
        shutil.copy2(source, target)
