"""Fuzzing a mosaic's frames: entries that are not files, earlier outputs re-saved, headers that declare
bombs, frames replaced while a run reads them. Each is named in one line, never dropped or drawn in silence."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from conftest import run_main
from mosaic_flights import SMALL, make_flight


@pytest.fixture
def frames(tmp_path) -> Path:
    folder = tmp_path / "frames"
    make_flight(folder, SMALL, seed=3)
    (folder / "ground_truth.json").unlink(missing_ok=True)
    return folder


def mosaic(monkeypatch, capfd, frames: Path, output: Path, *options: str) -> tuple[int, str]:
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(frames), "-o", str(output), "-m", "sift", "--quiet", "--overlap-pairs", "1", *options)
    return code, err


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes")
def test_links_to_nothing_link_loops_and_pipes_named_jpg_are_named_and_never_opened(frames, tmp_path, monkeypatch, capfd):
    (frames / "zz_dangling.jpg").symlink_to(tmp_path / "gone.jpg")
    (frames / "zz_loop_a.jpg").symlink_to(frames / "zz_loop_b.jpg")
    (frames / "zz_loop_b.jpg").symlink_to(frames / "zz_loop_a.jpg")
    os.mkfifo(frames / "zz_pipe.jpg")  # no writer: opening it to read would wait for ever
    (frames / "zz_linked.jpg").symlink_to(frames / "frame_000.jpg")  # a link to a frame is a frame
    code, err = mosaic(monkeypatch, capfd, frames, tmp_path / "m.png")
    assert code == 0, err
    assert f"skipping zz_dangling.jpg: a symbolic link to {tmp_path / 'gone.jpg'}, which does not exist" in err
    assert "skipping zz_loop_a.jpg: a loop of symbolic links" in err and "skipping zz_loop_b.jpg: a loop of symbolic links" in err
    assert "skipping zz_pipe.jpg: not a regular file (a pipe, device or socket)" in err
    report = json.loads((tmp_path / "m.json").read_text())
    skipped = {entry["file"] for entry in report["skipped_files"]}
    assert skipped == {"zz_dangling.jpg", "zz_loop_a.jpg", "zz_loop_b.jpg", "zz_pipe.jpg"}
    assert "zz_linked.jpg" in [frame["file"] for frame in report["frames"]]


@pytest.mark.parametrize("resave", [dict(sort_keys=True, indent=2), dict(separators=(",", ":"), sort_keys=True)], ids=["sorted", "compact"])
def test_an_earlier_mosaic_whose_sidecar_was_re_saved_is_still_not_a_frame(resave, frames, monkeypatch, capfd):
    code, err = mosaic(monkeypatch, capfd, frames, frames / "old.png")
    assert code == 0, err
    sidecar = frames / "old.json"
    sidecar.write_text(json.dumps(json.loads(sidecar.read_text()), **resave))  # as an editor or jq would save it
    assert not sidecar.read_text().startswith('{"format"') and not sidecar.read_text().startswith('{\n  "format"')
    code, err = mosaic(monkeypatch, capfd, frames, frames / "new.png")
    assert code == 0, err
    assert "skipping old.png: an earlier udh mosaic's output (old.json)" in err
    report = json.loads((frames / "new.json").read_text())
    assert not any(frame["file"].startswith("old.") for frame in report["frames"])
    assert report["summary"]["frames"] == len(list(frames.glob("frame_*.jpg")))


def test_a_mosaic_named_like_a_frame_does_not_hide_that_frame_from_the_next_run(frames, monkeypatch, capfd):
    count = len(list(frames.glob("frame_*.jpg")))
    code, err = mosaic(monkeypatch, capfd, frames, frames / "frame_003.png")  # its sidecar: frame_003.json
    assert code == 0, err
    code, err = mosaic(monkeypatch, capfd, frames, frames / "new.png")
    assert code == 0, err
    assert "skipping frame_003.png: an earlier udh mosaic's output (frame_003.json)" in err
    assert "skipping frame_003.jpg" not in err
    report = json.loads((frames / "new.json").read_text())
    assert "frame_003.jpg" in [frame["file"] for frame in report["frames"]]
    assert report["summary"]["frames"] == count  # the preview, frame_003.preview.jpg, is no frame either


def test_a_json_file_that_only_mentions_the_sidecar_format_is_not_a_sidecar(frames, monkeypatch, capfd):
    from udh_cli.mosaic.outputs.staging import SIDECAR_FORMAT, earlier_outputs

    (frames / "notes.json").write_text(json.dumps({"a": 1, "about": SIDECAR_FORMAT}, sort_keys=True))
    (frames / "notes.png").write_bytes((frames / "frame_000.jpg").read_bytes())
    assert earlier_outputs(sorted(frames.iterdir())) == {}


def jpeg_declaring(width: int, height: int, padding: int = 0) -> bytes:
    """A small JPEG whose frame header declares ``width`` x ``height``; ``padding`` bytes of comment segments make
    the file look large enough to hold them (the coded data stays a few hundred bytes)."""
    import struct

    import cv2

    from conftest import textured_image

    ok, encoded = cv2.imencode(".jpg", textured_image(64, 64, seed=1))
    data = bytearray(encoded.tobytes())
    start = data.find(b"\xff\xc0") + 5
    data[start:start + 4] = struct.pack(">HH", height, width)
    comments = b""
    while len(comments) < padding:
        comments += b"\xff\xfe" + struct.pack(">H", 60002) + bytes(60000)
    return bytes(data[:2] + comments + data[2:])


def test_frames_declaring_15000_squared_are_refused_before_any_decoder_sees_them(frames, tmp_path, monkeypatch, capfd):
    import cv2

    from udh_cli.mosaic.live.follow import ends_whole

    bomb = jpeg_declaring(15000, 15000, padding=60_000)  # under the old limit of pixels per byte of the whole file
    for number in range(4):
        (frames / f"zz_bomb{number}.jpg").write_bytes(bomb)
    decode = cv2.imdecode

    def guarded(buffer, flags):
        assert len(buffer) != len(bomb), "a frame declaring 15000x15000 pixels reached the decoder"
        return decode(buffer, flags)

    monkeypatch.setattr(cv2, "imdecode", guarded)
    code, err = mosaic(monkeypatch, capfd, frames, tmp_path / "m.png")
    assert code == 0, err
    for number in range(4):
        assert f"skipping zz_bomb{number}.jpg: cannot be decoded (the JPEG declares 15000x15000 pixels in only" in err
    assert json.loads((tmp_path / "m.json").read_text())["summary"]["frames"] == len(list(frames.glob("frame_*.jpg")))
    assert ends_whole(frames / "zz_bomb0.jpg", len(bomb))  # live mode: complete by its end marker, and never decoded


@pytest.mark.parametrize("change", ["rewritten", "replaced"])
def test_a_frame_changed_on_disk_after_its_pairs_were_estimated_is_refused_not_drawn(change, frames, tmp_path, monkeypatch, capfd):
    import shutil

    from udh_cli.mosaic import run as mosaic_run

    victim, other = frames / "frame_003.jpg", frames / "frame_005.jpg"
    solve = mosaic_run.solve_parts

    def solve_then_change(*args, **kwargs):  # between the pair estimates and the compositing, the file changes
        if change == "rewritten":
            victim.write_bytes(other.read_bytes())
        else:
            shutil.copy(other, tmp_path / "new.jpg")
            os.replace(tmp_path / "new.jpg", victim)
        return solve(*args, **kwargs)

    monkeypatch.setattr(mosaic_run, "solve_parts", solve_then_change)
    out = tmp_path / "out"
    out.mkdir()
    code, err = mosaic(monkeypatch, capfd, frames, out / "m.png")
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1, err
    assert lines[0].startswith(f"error: {victim}: changed on disk while the mosaic was made"), err
    assert not (out / "m.png").exists() and not (out / "m.json").exists()


def test_a_damaged_video_skips_the_frames_its_decoder_reports_and_says_so(tmp_path, monkeypatch, capfd):
    import cv2
    import numpy as np

    from conftest import textured_image

    video = tmp_path / "flight.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10, (320, 240))
    if not writer.isOpened():
        pytest.skip("OpenCV here cannot write MPEG-4 video")
    ground = cv2.cvtColor(textured_image(800, 600, seed=3), cv2.COLOR_GRAY2BGR)
    for number in range(20):
        writer.write(np.ascontiguousarray(ground[number * 10:number * 10 + 240, number * 12:number * 12 + 320]))
    writer.release()
    data = bytearray(video.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 400] = np.random.default_rng(0).integers(0, 256, 400, dtype=np.uint8).tobytes()  # a damaged stretch
    video.write_bytes(bytes(data))

    out = tmp_path / "out"
    out.mkdir()
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(video), "-o", str(out / "m.png"), "-m", "sift", "--quiet", "--overlap-pairs", "1")
    captured = capfd.readouterr()
    assert code == 0, err
    lines = [line for line in (err + captured.out).splitlines() if line.strip()]
    assert all(line.startswith("warning: ") for line in lines), lines  # FFmpeg's own lines stay off the terminal
    import re

    damaged = re.findall(r"warning: skipping flight\.mp4#(\d+): damaged \(the decoder says: ", err)  # the frame its damaged packet made
    stopped = re.search(r"warning: flight\.mp4: the decoder stopped after (\d+) of the 20 frames the video lists", err)
    assert damaged and stopped and all(int(number) < int(stopped.group(1)) for number in damaged), err
    report = json.loads((out / "m.json").read_text())
    named = {entry["file"] for entry in report["skipped_files"]}
    for line in lines:
        if line.startswith("warning: skipping "):
            assert line.split()[2].rstrip(":") in named
    assert report["summary"]["placed"] == report["summary"]["frames"] < 20


def test_a_dangling_link_removed_while_it_is_examined_is_named_not_a_traceback(tmp_path, monkeypatch):
    from udh_cli.mosaic.inputs import listing as listing_module

    link = tmp_path / "zz_dangling.jpg"
    link.symlink_to(tmp_path / "gone.jpg")

    def removed_meanwhile(path):
        raise FileNotFoundError(2, "No such file or directory", str(path))

    monkeypatch.setattr(listing_module.os, "readlink", removed_meanwhile)
    assert listing_module.not_a_file(link) == "a symbolic link to a missing file; copy the frame there or remove the link"


def test_damage_in_a_frame_every_drops_skips_the_next_kept_frame_decoded_from_it(tmp_path, monkeypatch):
    from udh_cli.mosaic.inputs import frames as frames_module
    from udh_cli.mosaic.report import Reporter

    from conftest import textured_image

    class Capture:  # the decoded frames are scripted: only what the decoder reports matters here
        def isOpened(self):
            return True

        def get(self, prop):
            return 10

        def release(self):
            pass

    damaged = {3: "error while decoding MB 4 5", 6: "concealing 40 DC errors"}  # 3 is dropped by --every 2, 6 is kept
    decoded = iter(range(11))

    def read_video_frame(capture):
        number = next(decoded)
        if number == 10:
            return False, None, None
        return True, textured_image(96, 64, seed=number), damaged.get(number)

    monkeypatch.setattr(frames_module, "_open_capture", lambda path: Capture())
    monkeypatch.setattr(frames_module, "read_video_frame", read_video_frame)
    video = tmp_path / "flight.mp4"
    video.write_bytes(b"\0" * 64)
    reporter = Reporter(quiet=True)
    frameset = frames_module._open_video(video, 64, 2, reporter, None)
    assert [f.name for f in frameset.frames] == ["flight.mp4#0", "flight.mp4#2", "flight.mp4#8"]
    assert [entry["file"] for entry in frameset.skipped] == ["flight.mp4#4", "flight.mp4#6"]
    assert frameset.skipped[0]["reason"] == "decoded from the damaged #3 (the decoder says: error while decoding MB 4 5)"
    assert frameset.skipped[1]["reason"] == "damaged (the decoder says: concealing 40 DC errors)"
    assert reporter.warnings[0] == "skipping flight.mp4#4: decoded from the damaged #3 (the decoder says: error while decoding MB 4 5)"
    assert [f.video_frame for f in frameset.frames] == [0, 2, 8]
