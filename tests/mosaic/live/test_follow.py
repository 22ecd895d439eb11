"""Live mode: a folder being written frame by frame, half-written frames included, becomes the same mosaic."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from udh_cli.errors import UdhError
from udh_cli.mosaic import FollowConfig, MosaicConfig, run_live, run_mosaic
from udh_cli.mosaic.live.follow import _Watch, poll_complete_frames


def test_a_frame_joins_only_once_it_stopped_changing(tmp_path):
    frame = tmp_path / "f1.bmp"  # a format without a structure to tell a whole file by: the settle rule decides
    frame.write_bytes(b"BM half")
    watch = _Watch()
    now = time.time() + 10  # old enough to have settled
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), now) == []  # first sight: not yet known to be still
    with frame.open("ab") as handle:  # the writer goes on
        handle.write(b" more")
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), now) == []  # it changed since the last look
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), now) == [frame]  # unchanged over two looks
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), now) == []  # and only once
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "f2.png").write_bytes(b"png")
    poll_complete_frames(tmp_path, watch, 1.0, {(tmp_path / "f2.png").resolve()}, now)
    assert poll_complete_frames(tmp_path, watch, 1.0, {(tmp_path / "f2.png").resolve()}, now) == []  # excluded: an output


@pytest.mark.parametrize("suffix", [".jpg", ".png", ".tif"])
def test_a_frame_whose_writer_pauses_half_way_joins_only_once_it_is_whole(suffix, tmp_path):
    import cv2

    from conftest import textured_image

    ok, encoded = cv2.imencode(suffix, textured_image(160, 120, seed=2))
    data = encoded.tobytes()
    frame = tmp_path / f"f{suffix}"
    frame.write_bytes(data[: len(data) // 2])
    watch, later = _Watch(), time.time() + 10  # long after the first half: settled by size, age and two looks
    for _ in range(3):
        assert poll_complete_frames(tmp_path, watch, 1.0, set(), later) == []  # its structure says it is not whole
    with frame.open("ab") as handle:  # the writer goes on after its pause
        handle.write(data[len(data) // 2 :])
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), later) == [frame]


@pytest.mark.parametrize("trailer", [bytes(64), b"MotionPhoto_Data" + bytes(300)])
def test_a_whole_jpeg_with_bytes_after_its_end_marker_joins_once_settled(trailer, tmp_path):
    import cv2

    from conftest import textured_image

    frame = tmp_path / "f.jpg"
    frame.write_bytes(cv2.imencode(".jpg", textured_image(160, 120, seed=3))[1].tobytes() + trailer)
    watch, later = _Watch(), time.time() + 10
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), later) == []  # first sight: not yet known to be still
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), later) == [frame]  # settled, and it decodes whole


def test_after_the_flight_a_frame_that_never_became_whole_joins_for_the_run_to_refuse(tmp_path):
    frame = tmp_path / "f.jpg"
    frame.write_bytes(b"\xff\xd8" + bytes(200))  # cut short for good
    watch, later = _Watch(), time.time() + 10
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), later) == []
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), later) == []  # settled, but not whole: the flight goes on
    assert poll_complete_frames(tmp_path, watch, 1.0, set(), later, flight_over=True) == [frame]


def test_a_flight_written_while_it_is_followed_gives_the_mosaic_of_the_whole_folder(tmp_path):
    from mosaic_flights import SMALL, make_flight

    source = tmp_path / "source"
    source.mkdir()
    make_flight(source, SMALL, seed=4)
    frames = sorted(source.glob("frame_*.jpg"))
    live = tmp_path / "live"
    live.mkdir()

    def fly():
        for number, path in enumerate(frames):  # each frame written in two halves, 0.15 s apart, as a slow copy would
            if number == len(frames) // 2:  # the flight goes on after the first refresh, however slow its process starts
                deadline = time.monotonic() + 60
                while not (tmp_path / "out" / "live.json").exists() and time.monotonic() < deadline:
                    time.sleep(0.05)
            data = path.read_bytes()
            target = live / path.name
            target.write_bytes(data[: len(data) // 2])
            time.sleep(0.15)
            with target.open("ab") as handle:
                handle.write(data[len(data) // 2 :])
            time.sleep(0.1)
        (live / "DONE").write_text("")

    (tmp_path / "out").mkdir()
    writer = threading.Thread(target=fly)
    writer.start()
    config = MosaicConfig(method="sift")
    follow = FollowConfig(refresh_every=2, poll_s=0.05, settle_s=0.2, idle_timeout_s=30.0)
    report = run_live(live, tmp_path / "out" / "live.png", config, follow)
    writer.join()
    assert report["live"]["ended_by"] == "sentinel" and report["live"]["frames"] == len(frames)
    assert report["skipped_files"] == []  # the DONE file is the sentinel, not a frame that failed to read
    assert report["live"]["refreshes"] >= 2  # the mosaic was rewritten while the flight went on
    assert report["summary"]["placed"] == len(frames) and report["summary"]["parts"] == 1
    assert report["summary"]["pairs_from_cache"] > 0  # the final run reused the refreshes' pairs
    written = json.loads((tmp_path / "out" / "live.json").read_text())
    assert written["live"] == report["live"]  # the sidecar on disk says how the live run went
    page = (tmp_path / "out" / "live.report.html").read_text()
    assert "<title>udh mosaic of live</title>" in page and "refreshes, ended by sentinel" in page  # not the staging folder
    assert report["timings_s"]["total"] >= sum(v for k, v in report["timings_s"].items() if k != "total") - 1e-6  # the last run's own
    whole = run_mosaic(source, tmp_path / "whole.png", config)
    for frame, expected in zip(report["frames"], whole["frames"], strict=True):
        np.testing.assert_allclose(frame["mosaic_from_frame"], expected["mosaic_from_frame"], atol=1e-6)
    assert not any(p.name.startswith(".udh-follow") for p in (tmp_path / "out").iterdir())  # the staging folder is gone
    # The quick look drew every frame as it came (0.1-0.4 s after its last byte here; the bound allows a busy machine).
    look = json.loads((tmp_path / "out" / "live.live.json").read_text())
    assert [f["name"] for f in look["frames"]] == [p.name for p in frames] and look["frames_placed"] == len(frames)
    assert max(f["latency_s"] for f in look["frames"]) < 5.0
    assert (tmp_path / "out" / "live.live.jpg").is_file()


def test_a_flight_that_never_starts_ends_with_a_clear_error(tmp_path):
    (tmp_path / "out").mkdir()
    with pytest.raises(UdhError, match="ended with 0 complete frame"):
        run_live(tmp_path, tmp_path / "out" / "m.png", MosaicConfig(method="sift"), FollowConfig(poll_s=0.02, idle_timeout_s=0.2))
    with pytest.raises(UdhError, match="not a folder"):
        run_live(tmp_path / "nothing", tmp_path / "out" / "m.png", MosaicConfig(method="sift"))


def _arrivals(batches: list, live: Path):
    """A fake clock for follow_mosaic: the first batch of frames is in ``live`` at once, each poll brings the next,
    then the DONE file. Returns (the clock's reading as a one-item list, its sleep)."""
    import shutil

    now, polls = [0.0], [0]

    def sleep(seconds):
        now[0] += seconds
        polls[0] += 1
        for path in (batches[polls[0]] if polls[0] < len(batches) else []):
            shutil.copy(path, live / path.name)
        if polls[0] == len(batches):
            (live / "DONE").write_text("")

    for path in batches[0]:
        shutil.copy(path, live / path.name)
    return now, sleep


def test_a_refresh_that_fails_or_whose_process_dies_does_not_end_the_flight(tmp_path):
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    from mosaic_flights import make_flight
    from udh_cli.mosaic.live.follow import follow_mosaic
    from udh_cli.mosaic.report import Reporter
    from udh_cli.simulate import FlightConfig

    source, live = tmp_path / "source", tmp_path / "live"
    frames = make_flight(source, FlightConfig(frame_size=(160, 120), strips=2, frames_per_strip=6, focal_px=150.0), seed=1)
    live.mkdir()
    batches = [frames[:4], frames[4:8], frames[8:]]
    now, sleep = _arrivals(batches, live)
    failures = iter([RuntimeError("a bug in a refresh"), BrokenProcessPool("killed")])

    def start_refresh(folder):
        future = Future()
        future.set_exception(next(failures))
        return future

    runs = []

    def run(folder):
        runs.append(folder)
        held = len(list(folder.glob("*.jpg")))
        return {"summary": {"placed": held, "frames": held}}

    reporter = Reporter(quiet=True)
    report = follow_mosaic(live, tmp_path / "m.png", run, FollowConfig(refresh_every=4, poll_s=0.1, idle_timeout_s=60.0), reporter,
                           clock=lambda: now[0], sleep=sleep, start_refresh=start_refresh)
    assert any("RuntimeError: a bug in a refresh" in w for w in reporter.warnings)
    assert any("refresh process stopped" in w for w in reporter.warnings)
    # After the process died, the third refresh ran here; it held all 12 frames, so no final run came after it.
    assert len(runs) == 1 and runs[0] != live
    assert report["live"] == {"refreshes": 1, "frames": 12, "ended_by": "sentinel", "final": "the last refresh"}


def test_the_quick_look_s_failures_are_warnings_in_a_live_run(tmp_path, monkeypatch):
    from mosaic_flights import SMALL, make_flight
    from udh_cli.mosaic.live import quicklook
    from udh_cli.mosaic.report import Reporter

    folder = tmp_path / "flight"
    make_flight(folder, SMALL, seed=4)
    (folder / "DONE").write_text("")

    def broken(self, path, seen_at=None):
        raise OSError("disk full")

    monkeypatch.setattr(quicklook.QuickLook, "add", broken)
    (tmp_path / "out").mkdir()
    reporter = Reporter(quiet=True)
    report = run_live(folder, tmp_path / "out" / "m.png", MosaicConfig(method="sift"), FollowConfig(poll_s=0.01, idle_timeout_s=5.0), reporter)
    assert report["summary"]["placed"] == 8
    assert sum("could not be drawn in the quick look (OSError: disk full)" in w for w in reporter.warnings) == 8
    with pytest.raises(UdhError, match="cannot follow a flight"):
        run_live(folder, tmp_path / "out" / "m.png", MosaicConfig(method="sift"), camera="estimate")


def test_the_final_run_comes_only_when_the_last_refresh_missed_frames(tmp_path):
    """A refresh after 8 of 12 frames: the last 4 came after it, so a final run over the folder makes the map."""
    from mosaic_flights import make_flight
    from udh_cli.mosaic.live.follow import follow_mosaic
    from udh_cli.simulate import FlightConfig

    source, live = tmp_path / "source", tmp_path / "live"
    frames = make_flight(source, FlightConfig(frame_size=(160, 120), strips=2, frames_per_strip=6, focal_px=150.0), seed=1)
    live.mkdir()
    batches = [frames[:8], frames[8:]]
    now, sleep = _arrivals(batches, live)
    runs = []

    def run(folder, live=None):
        runs.append((folder, live))
        held = len(list(folder.glob("*.jpg")))
        return {"summary": {"placed": held, "frames": held}}

    report = follow_mosaic(live, tmp_path / "m.png", run, FollowConfig(refresh_every=8, poll_s=0.1, idle_timeout_s=60.0),
                           clock=lambda: now[0], sleep=sleep)
    assert len(runs) == 2 and runs[0][0] != live and runs[-1][0] == live
    record = {"refreshes": 1, "frames": 12, "ended_by": "sentinel", "final": "a final run"}
    assert runs[0][1] is None and runs[-1][1] == record  # the final run writes the flight's record itself
    assert report["summary"]["frames"] == 12 and report["live"] == record


def test_a_refresh_in_the_refresher_process_stops_on_ctrl_c_and_the_idle_process_ignores_it(monkeypatch):
    """The refresher ignores Ctrl-C while idle (no traceback); during a refresh Ctrl-C stops it like the main run,
    so the end of the flight never waits for a whole refresh."""
    import signal

    from udh_cli.mosaic.live import run as live_run

    seen = []
    monkeypatch.setattr(live_run, "_live_run", lambda *args: seen.append(signal.getsignal(signal.SIGINT)) or {})
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as die_with_parent leaves the idle refresher
    try:
        assert live_run._refresh_in_worker(Path("f"), Path("m.png"), None, Path("m.pairs.json"), {}) == {}
        assert seen == [signal.default_int_handler] and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
