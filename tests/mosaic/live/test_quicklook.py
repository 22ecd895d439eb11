"""The live quick look: frames chained as they arrive, drawn at once, measured against the simulator's truth."""

from __future__ import annotations

import json

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.estimators import create_estimator
from udh_cli.mosaic.live.follow import ends_whole, tiff_whole
from udh_cli.mosaic.pairs.types import Acceptance
from udh_cli.mosaic.live.quicklook import FRAME_SIDE, QuickLook
from udh_cli.mosaic.outputs.files import RunFiles
from udh_cli.simulate import load_ground_truth

from mosaic_flights import ACCURATE, make_flight


def test_the_quick_look_chains_a_flight_within_pixels_of_the_truth(tmp_path):
    folder = tmp_path / "flight"
    frames = make_flight(folder, ACCURATE, seed=4)
    truth = load_ground_truth(folder / "ground_truth.json")["ground_from_frame"]
    output = tmp_path / "m.png"
    look = QuickLook(output, [create_estimator("sift")], Acceptance(), work_size=800)
    records = [look.add(path) for path in frames]
    assert [r["placed"] for r in records] == [True] * len(frames)
    assert records[0]["stage"] == "first frame" and all(r["latency_s"] is not None and r["drawn_at"] >= r["seen_at"] for r in records)
    ground_from_ref = np.asarray(truth[frames[0].name])
    errors = []
    for path, record in zip(frames, records):
        expected = np.linalg.inv(ground_from_ref) @ np.asarray(truth[path.name])
        errors.append(geometry.mace(np.asarray(record["ref_from_frame"]), expected, *ACCURATE.frame_size))
    assert max(errors) < 3.0  # a chain of SIFT pairs on 480x360 frames: drift of a few pixels at most
    # The picture shows every frame at about FRAME_SIDE px, and what it covers agrees with the truth's union.
    picture = cv2.imread(str(RunFiles(output).live_picture))
    assert picture is not None and FRAME_SIDE < max(picture.shape[:2]) < 10 * FRAME_SIDE
    written = json.loads(RunFiles(output).live_record.read_text())
    assert written["format"].startswith("udh-mosaic") and written["frames_placed"] == len(frames)
    assert [f["name"] for f in written["frames"]] == [p.name for p in frames]


def test_a_frame_that_fails_is_left_out_and_the_next_one_goes_on_from_the_last_placed(tmp_path):
    folder = tmp_path / "flight"
    frames = make_flight(folder, ACCURATE, seed=4)
    noise = tmp_path / "noise.jpg"
    cv2.imwrite(str(noise), np.random.default_rng(0).integers(0, 255, (360, 480, 3), dtype=np.uint8))
    look = QuickLook(tmp_path / "m.png", [create_estimator("sift")], Acceptance(), work_size=800)
    records = [look.add(p) for p in [frames[0], frames[1], noise, frames[2]]]
    assert [r["placed"] for r in records] == [True, True, False, True]
    assert records[2]["failure"]  # says why
    truth = load_ground_truth(folder / "ground_truth.json")["ground_from_frame"]
    expected = np.linalg.inv(np.asarray(truth[frames[0].name])) @ np.asarray(truth[frames[2].name])
    assert geometry.mace(np.asarray(records[3]["ref_from_frame"]), expected, *ACCURATE.frame_size) < 3.0
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"not an image")
    record = look.add(broken)
    assert not record["placed"] and "broken.jpg" in record["failure"]


def test_the_picture_grows_and_halves_to_hold_a_long_flight(tmp_path, monkeypatch):
    import udh_cli.mosaic.live.quicklook as quicklook

    monkeypatch.setattr(quicklook, "MAX_SIDE", 700)
    folder = tmp_path / "flight"
    frames = make_flight(folder, ACCURATE, seed=4)
    look = QuickLook(tmp_path / "m.png", [create_estimator("sift")], Acceptance(), work_size=800)
    records = [look.add(p) for p in frames]
    assert all(r["placed"] for r in records)
    assert max(look.picture.shape[:2]) <= 700
    shown = look.shown()
    assert (shown != quicklook.BACKGROUND).any(axis=2).mean() > 0.5  # cropped to the frames, all of them in it
    written = cv2.imread(str(RunFiles(tmp_path / "m.png").live_picture))
    assert written.shape == shown.shape


def test_a_jpeg_or_png_is_whole_once_its_end_marker_is_written_and_it_decodes(tmp_path):
    image = np.random.default_rng(1).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    for suffix in (".jpg", ".png"):
        ok, encoded = cv2.imencode(suffix, image)
        data = encoded.tobytes()
        path = tmp_path / f"f{suffix}"
        path.write_bytes(data[: len(data) // 2])
        assert not ends_whole(path, path.stat().st_size)  # half-written
        path.write_bytes(data)
        assert ends_whole(path, path.stat().st_size)
        path.write_bytes(data[:100] + data[-12:])  # the right ending, but not an image: a cut copy
        assert not ends_whole(path, path.stat().st_size)
    tiff = tmp_path / "f.tif"
    cv2.imwrite(str(tiff), image)
    assert not ends_whole(tiff, tiff.stat().st_size)  # no end marker: its strips tell instead
    assert tiff_whole(tiff, tiff.stat().st_size)
    data = tiff.read_bytes()
    tiff.write_bytes(data[: len(data) - 100])
    assert not tiff_whole(tiff, tiff.stat().st_size)
