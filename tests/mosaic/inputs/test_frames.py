"""Frame input details: EXIF capture-time order, natural name order, working copies, wrong loop closures."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import Estimator, create_estimator
from udh_cli.mosaic import MosaicConfig, run_mosaic
from udh_cli.mosaic.inputs.metadata import capture_time, read_metadata
from udh_cli.mosaic.inputs.frames import open_frames

from conftest import textured_image
from mosaic_flights import SMALL, fingerprint, make_flight, work_fingerprints


def _jpeg_with_time(path: Path, image: np.ndarray, when: str) -> None:
    """A JPEG whose APP1 EXIF block holds DateTimeOriginal (in the Exif IFD) = ``when``."""
    text = when.encode() + b"\x00"  # 20 bytes
    # TIFF header, IFD0 with one entry (Exif IFD pointer), Exif IFD with one entry (DateTimeOriginal), string.
    ifd0, exif_ifd = 8, 8 + 2 + 12 + 4
    string_at = exif_ifd + 2 + 12 + 4
    tiff = b"II*\x00" + struct.pack("<I", ifd0)
    tiff += struct.pack("<H", 1) + struct.pack("<HHII", 0x8769, 4, 1, exif_ifd) + struct.pack("<I", 0)
    tiff += struct.pack("<H", 1) + struct.pack("<HHII", 0x9003, 2, len(text), string_at) + struct.pack("<I", 0)
    tiff += text
    payload = b"Exif\x00\x00" + tiff
    app1 = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    encoded = cv2.imencode(".jpg", image)[1].tobytes()
    path.write_bytes(encoded[:2] + app1 + encoded[2:])


def test_order_by_capture_time_and_by_natural_name(tmp_path):
    times = {"frame_2.jpg": "2020:01:01 10:00:03", "frame_10.jpg": "2020:01:01 10:00:01", "frame_1.jpg": "2020:01:01 10:00:02"}
    for seed, (name, when) in enumerate(times.items()):
        _jpeg_with_time(tmp_path / name, textured_image(64, 48, seed), when)
    assert capture_time(tmp_path / "frame_10.jpg") == "2020:01:01 10:00:01"
    by_name = open_frames(tmp_path, 800, order="name")
    assert [f.name for f in by_name.frames] == ["frame_1.jpg", "frame_2.jpg", "frame_10.jpg"]
    by_time = open_frames(tmp_path, 800, order="time")
    assert [f.name for f in by_time.frames] == ["frame_10.jpg", "frame_1.jpg", "frame_2.jpg"]
    assert capture_time(tmp_path / "missing.jpg") is None


def test_working_copies_are_small_and_grey(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((900, 1600, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((900, 1600, 3), np.uint8))
    frames = open_frames(tmp_path, 800).frames
    assert frames[0].size == (1600, 900) and frames[0].work_size == (800, 450) and frames[0].work.ndim == 2


class ShiftLoops(Estimator):
    """SIFT, except that loop-closure pairs (pre-warped, so B matches no frame) come back 60 px off: all of them,
    or the first ``wrong`` (as from a drifted chain's prior)."""

    name = "shift-loops"

    def __init__(self, prints, wrong: int | None = None):
        self.known = set(prints)
        self.sift = create_estimator("sift")
        self.wrong = wrong

    def _estimate(self, pair):
        image_b = pair.b
        homography, confidence, details = self.sift._estimate(pair)
        if fingerprint(image_b) not in self.known and (self.wrong is None or self.wrong > 0):
            self.wrong = None if self.wrong is None else self.wrong - 1
            homography = geometry.translation(60.0, 0.0) @ homography
        return homography, confidence, details


def test_loop_closures_that_contradict_the_chain_are_rejected(tmp_path):
    paths = make_flight(tmp_path / "f", SMALL, seed=4)
    # min_verified=0: the alignment check would catch these first; this test is about the chain's check of the
    # estimator's answers, so none is confirmed from the prediction instead.
    config = MosaicConfig(overlap_per_frame=1, min_verified=0, confirm_loops=False)
    report = run_mosaic(tmp_path / "f", tmp_path / "m.png", config, estimator=ShiftLoops(work_fingerprints(paths)))
    loops = [p for p in report["pairs"] if p["kind"] == "overlap"]
    # Rejected against the chain, tried again from a solve with the accepted loop pairs (none), rejected again.
    assert loops and all(p["status"] == "rejected" and "away from the solved prediction" in p["reason"] for p in loops)
    assert report["summary"]["placed"] == 8
    assert report["ground_truth_error"]["solved"]["max_corner_px"] < 3  # the wrong pairs did not reach the solve


def test_loop_closures_rejected_against_the_chain_are_tried_again_from_the_solve(tmp_path):
    paths = make_flight(tmp_path / "f", SMALL, seed=4)
    config = MosaicConfig(overlap_per_frame=1, min_verified=0, confirm_loops=False)  # the estimator answers every loop pair
    first = run_mosaic(tmp_path / "f", tmp_path / "m.png", config, estimator=ShiftLoops(work_fingerprints(paths)))
    first_round = {(p["a"], p["b"]) for p in first["pairs"] if p["kind"] == "overlap"}
    # The first round's answers are all wrong and rejected; the later rounds' are right and kept, and the solve
    # they allow shows overlaps that the chain did not (frames further apart).
    report = run_mosaic(tmp_path / "f", tmp_path / "n.png", config, estimator=ShiftLoops(work_fingerprints(paths), len(first_round)))
    loops = {(p["a"], p["b"]): p for p in report["pairs"] if p["kind"] == "overlap"}
    assert first_round <= set(loops) and all(p["status"] == "ok" for p in loops.values())
    assert {"loop-closure pairs", "loop-closure pairs again, from the solve (2)"} <= set(report["timings_s"])
    assert report["loop_consistency"]["loops_after"]["count"] == len(loops)
    assert report["ground_truth_error"]["solved"]["max_corner_px"] < 3


def test_unlistable_folders_give_a_clear_error(tmp_path, monkeypatch):
    (tmp_path / "frames" / "locked").mkdir(parents=True)
    listing = Path.iterdir

    def refuse(names: set[str]) -> None:
        def iterdir(self):
            if self.name in names:
                raise PermissionError(13, "Permission denied")
            return listing(self)

        monkeypatch.setattr(Path, "iterdir", iterdir)

    refuse({"locked"})  # an unreadable subfolder only loses its "did you mean" hint
    with pytest.raises(UdhError, match="no image files found"):
        open_frames(tmp_path / "frames", 800)
    refuse({"frames"})
    with pytest.raises(UdhError, match=r"cannot list the folder \(Permission denied\)"):
        open_frames(tmp_path / "frames", 800)


def test_narrow_range_16_bit_frames_mosaic_as_well_as_their_8_bit_originals(tmp_path):
    """Thermal-like frames (7000-8000 of 65535): one flight-wide stretch for the work copies and the mosaic."""
    import json

    from mosaic_flights import SMALL, make_flight
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.mosaic.inputs.frames import open_frames

    eight = tmp_path / "eight"
    eight.mkdir()
    make_flight(eight, SMALL, seed=5)
    sixteen = tmp_path / "sixteen"
    sixteen.mkdir()
    for path in sorted(eight.glob("frame_*.jpg")):
        grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(np.float64)
        cv2.imwrite(str(sixteen / path.with_suffix(".png").name), (7000 + grey / 255 * 1000).astype(np.uint16))
    (sixteen / "ground_truth.json").write_text((eight / "ground_truth.json").read_text().replace(".jpg", ".png"))

    frames = open_frames(sixteen, 800)
    low, high = frames.value_range
    assert 7000 / 65535 - 1e-3 < low < high < 8000 / 65535 + 1e-3
    assert all(f.work.dtype == np.uint8 and np.percentile(f.work, 99) - np.percentile(f.work, 1) > 100 for f in frames.frames)

    config = MosaicConfig(method="sift", overlap_per_frame=1)
    reference = run_mosaic(eight, tmp_path / "eight.png", config)
    thermal = run_mosaic(sixteen, tmp_path / "sixteen.png", config)
    assert thermal["summary"]["placed"] == reference["summary"]["placed"] == 8 and thermal["summary"]["parts"] == 1
    assert thermal["ground_truth_error"]["solved"]["mean_corner_px"] < reference["ground_truth_error"]["solved"]["mean_corner_px"] + 0.2
    mosaic = cv2.imread(str(tmp_path / "sixteen.png"), cv2.IMREAD_UNCHANGED)
    covered = mosaic[..., 3] > 0
    assert mosaic.dtype == np.uint8 and np.percentile(mosaic[..., 0][covered], 99) > 150  # not 0-35 of 255
    assert json.loads((tmp_path / "sixteen.json").read_text())["display_range"]["high"] == pytest.approx(high)


def test_metadata_reads_gps_camera_and_dji_flight_data(tmp_path):
    from PIL import Image

    path = tmp_path / "dji.jpg"
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = "DJI", "FC300S"
    gps = exif.get_ifd(0x8825)
    gps.update({1: "S", 2: (33.0, 51.0, 54.0), 3: "W", 4: (70.0, 30.0, 0.0), 5: b"\x00", 6: 123.5})
    xmp = b'<x:xmpmeta><rdf:Description drone-dji:RelativeAltitude="+60.20" drone-dji:FlightYawDegree="-87.4"/></x:xmpmeta>'
    Image.fromarray(textured_image(64, 48)).save(path, exif=exif, xmp=xmp)
    found = read_metadata(path)
    assert found.latitude == pytest.approx(-(33 + 51 / 60 + 54 / 3600)) and found.longitude == pytest.approx(-70.5)
    assert found.altitude_m == pytest.approx(123.5) and found.has_gps and found.camera == "DJI FC300S"
    assert found.relative_altitude_m == pytest.approx(60.2) and found.flight_yaw_deg == pytest.approx(-87.4)
    assert read_metadata(tmp_path / "missing.jpg") == type(found)()  # nothing known, no error
    plain = tmp_path / "plain.png"
    cv2.imwrite(str(plain), textured_image(64, 48))
    assert not read_metadata(plain).has_gps and read_metadata(plain).to_json() == {}


def test_metadata_of_a_real_dji_flight(shared_data):
    folder = shared_data / "flights" / "brighton-beach" / "images"
    first = read_metadata(sorted(folder.iterdir())[0])
    assert first.has_gps and 46.8 < first.latitude < 46.9 and -92.1 < first.longitude < -91.9
    assert first.focal_length_mm == pytest.approx(3.61) and first.capture_time.startswith("2016:06:23")


def test_the_camera_make_is_named_once_and_the_original_size_is_read(tmp_path):
    from PIL import Image

    from udh_cli.mosaic.inputs.metadata import camera_name

    assert camera_name("Canon", "Canon PowerShot ELPH 300 HS") == "Canon PowerShot ELPH 300 HS"
    assert camera_name("DJI", "FC300S") == "DJI FC300S" and camera_name(None, "FC300S") == "FC300S" and camera_name(None, None) is None
    path = tmp_path / "canon.jpg"
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = "Canon", "Canon EOS DIGITAL REBEL XSi"
    exif.get_ifd(0x8769).update({0xA002: 4272, 0xA003: 2848})  # the original's size, kept by a downscaled copy
    Image.fromarray(textured_image(64, 48)).save(path, exif=exif)
    found = read_metadata(path)
    assert found.camera == "Canon EOS DIGITAL REBEL XSi" and (found.original_width, found.original_height) == (4272, 2848)


def test_the_first_frames_decoded_while_reading_are_handed_over_once_as_full_images_gives_them(tmp_path):
    for seed in range(4):
        cv2.imwrite(str(tmp_path / f"f{seed}.png"), textured_image(160, 120, seed))
    one_frame = cv2.imread(str(tmp_path / "f0.png"), cv2.IMREAD_UNCHANGED).nbytes
    frameset = open_frames(tmp_path, 80, keep_decoded_bytes=2 * one_frame + 100)
    assert sorted(frameset.decoded_while_reading) == [0, 1]  # the first ones, within the budget
    assert open_frames(tmp_path, 80).decoded_while_reading == {}  # none unless asked
    taken = frameset.take_decoded([1, 2, 3])
    assert sorted(taken) == [1]
    assert np.array_equal(taken[1], dict(frameset.full_images([1]))[1])
    assert frameset.take_decoded([1]) == {} and sorted(frameset.decoded_while_reading) == [0]  # handed over once
    (tmp_path / "f0.png").write_bytes(cv2.imencode(".png", textured_image(160, 120, 9))[1].tobytes())
    with pytest.raises(UdhError, match="f0.png"):  # a frame replaced since it was read is refused, kept or not
        frameset.take_decoded([0])


@pytest.mark.parametrize("grey", [False, True])
def test_kept_16_bit_frames_are_handed_over_in_the_flights_grey_range_as_a_second_read_is(tmp_path, grey):
    for seed in range(3):
        image = textured_image(160, 120, seed).astype(np.uint16) * 4 + 7000  # thermal-like: a sliver of 16 bits
        cv2.imwrite(str(tmp_path / f"f{seed}.png"), image if grey else np.dstack([image, image // 2 + 3500, image]))
    frameset = open_frames(tmp_path, 80, keep_decoded_bytes=2**30)
    assert frameset.value_range is not None and frameset.decoded_while_reading[0].dtype == np.uint16
    taken = frameset.take_decoded([0, 2])
    read_again = dict(frameset.full_images([0, 2]))
    for index in (0, 2):
        assert taken[index].dtype == np.uint8 and taken[index].shape == (120, 160, 3)
        assert np.array_equal(taken[index], read_again[index])
