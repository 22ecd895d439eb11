"""Lens distortion: cameras.json, undistorting frames and ground-control pixels, and a distorted flight."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from udh_cli.errors import UdhError
from udh_cli.mosaic import MosaicConfig, run_mosaic
from udh_cli.mosaic.inputs.lens import Lens, read_cameras

from mosaic_flights import SMALL, distort, make_flight

BARREL = {"projection_type": "brown", "width": 320, "height": 240, "focal_x": 0.8, "focal_y": 0.8, "c_x": 0.01, "c_y": -0.01,
          "k1": -0.15, "k2": 0.02, "p1": 0.0, "p2": 0.0, "k3": 0.0}


def write_cameras(path, **cameras):
    path.write_text(json.dumps(cameras))
    return path


def test_a_cameras_json_is_read_in_opensfm_units(tmp_path):
    lens = read_cameras(write_cameras(tmp_path / "cameras.json", **{"v2 dji fc330 4000 3000 brown 0.55": BARREL}))
    assert (lens.width, lens.height, lens.k1, lens.k2) == (320, 240, -0.15, 0.02)
    k = lens.matrix((640, 480))  # twice the calibrated size: the same camera in pixels twice as large
    np.testing.assert_allclose(k, [[512, 0, 319.5 + 6.4, ], [0, 512, 239.5 - 6.4], [0, 0, 1]])
    perspective = read_cameras(write_cameras(tmp_path / "p.json", cam={"projection_type": "perspective", "width": 4000,
                                                                         "height": 3000, "focal": 0.6, "k1": -0.1, "k2": 0.01}))
    assert perspective.focal_x == perspective.focal_y == 0.6 and perspective.c_x == 0.0


@pytest.mark.parametrize("cameras, message", [
    ({"a": BARREL, "b": BARREL}, "2 cameras"),
    ({"a": {**BARREL, "projection_type": "fisheye"}}, "fisheye projection"),
    ({"a": {**BARREL, "focal_x": 3600.0}}, "over the frame's longer side"),
    ({"a": {**BARREL, "k1": "big"}}, "finite number for 'k1'"),
    ({"a": {**BARREL, "k1": 80.0}}, "far beyond any real lens"),
    ({}, "expected a JSON object of cameras"),
])
def test_bad_camera_files_are_one_line_errors(tmp_path, cameras, message):
    with pytest.raises(UdhError, match=message):
        read_cameras(write_cameras(tmp_path / "cameras.json", **cameras))
    with pytest.raises(UdhError, match="no such file"):
        read_cameras(tmp_path / "missing.json")


def test_undistorting_undoes_the_lens_on_points_and_images():
    lens = Lens(320, 240, 0.8, 0.8, 0.01, -0.01, k1=-0.15, k2=0.02)
    pinhole = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 255, (240, 320, 3), np.uint8), (0, 0), 2)
    distorted = distort(pinhole, lens)
    corner_shift = np.abs(distorted.astype(int) - pinhole).mean()
    restored = lens.undistort(distorted)
    inner = (slice(30, 210), slice(40, 280))  # barrel distortion pushes the frame's rim outside it
    assert np.abs(restored[inner].astype(int) - pinhole[inner]).mean() < 0.25 * corner_shift
    # Points: a distorted corner pixel goes back to where the pinhole camera saw it, well away from the rim.
    k = lens.matrix((320, 240))
    seen = np.array([[10.0, 10.0], [300.0, 220.0], [160.0, 120.0]])
    normalised = (seen - k[:2, 2]) / k[0, 0]
    projected, _ = cv2.projectPoints(np.c_[normalised, np.ones(3)], np.zeros(3), np.zeros(3), k, lens.coefficients())
    np.testing.assert_allclose(lens.undistort_points(projected.reshape(-1, 2), (320, 240)), seen, atol=0.01)


def test_a_camera_of_another_shape_is_refused(tmp_path):
    folder = tmp_path / "flight"
    make_flight(folder, SMALL, seed=4)
    cameras = write_cameras(tmp_path / "cameras.json", cam={**BARREL, "width": 4000, "height": 2250})
    with pytest.raises(UdhError, match="calibrated on 4000x2250 frames"):
        run_mosaic(folder, tmp_path / "m.png", MosaicConfig(method="sift"), camera=cameras)
    assert not (tmp_path / "m.png").exists()


def test_a_distorted_flight_mosaics_to_its_truth_only_with_its_camera(tmp_path):
    folder = tmp_path / "flight"
    paths = make_flight(folder, SMALL, seed=4)
    lens = Lens(320, 240, 0.8, 0.8, 0.01, -0.01, k1=-0.15, k2=0.02)
    for path in paths:  # the simulator's pinhole frames as a barrel lens would have taken them
        cv2.imwrite(str(path), distort(cv2.imread(str(path)), lens), [cv2.IMWRITE_JPEG_QUALITY, 95])
    cameras = write_cameras(tmp_path / "cameras.json", cam=BARREL)
    config = MosaicConfig(method="sift")
    plain = run_mosaic(folder, tmp_path / "plain.png", config)
    undistorted = run_mosaic(folder, tmp_path / "undistorted.png", config, camera=cameras)
    error = lambda report: report["ground_truth_error"]["solved"]["mean_corner_px"]  # noqa: E731
    assert undistorted["camera"]["k1"] == -0.15 and plain["camera"] is None
    # Measured: 21.4 px without the camera, 0.81 with it (0.24 on the pinhole frames themselves; the distorted
    # frames were resampled twice and JPEG-coded once more).
    assert error(undistorted) < 1.0 and error(plain) > 10.0


def test_ground_control_pixels_are_undistorted_in_the_file_s_own_units():
    from udh_cli.mosaic.georef.gcp import GcpFile, Observation, undistorted_observations

    lens = Lens(320, 240, 0.8, 0.8, k1=-0.15)
    seen = [Observation(0, 0, 0, 20.0, 15.0, "a.jpg", "p1", 2), Observation(0, 0, 0, 40.0, 30.0, "b.jpg", "p1", 3),
            Observation(0, 0, 0, 5.0, 5.0, "gone.jpg", "p2", 4)]
    moved = undistorted_observations(GcpFile(32633, seen), lens, {"a.jpg": (320, 240), "b.jpg": (640, 480)}, image_width=320)
    expected = lens.undistort_points(np.array([[20.0, 15.0]]), (320, 240))[0]
    assert (moved.observations[0].px, moved.observations[0].py) == pytest.approx(tuple(expected), abs=1e-9)
    assert np.hypot(*(expected - [20.0, 15.0])) > 3  # a corner point moves outwards by pixels
    # b.jpg is 640 wide and the file refers to 320-px images: undistorted at 640, given back at 320
    twice = lens.undistort_points(np.array([[80.0, 60.0]]), (640, 480))[0] / 2
    assert (moved.observations[1].px, moved.observations[1].py) == pytest.approx(tuple(twice), abs=1e-9)
    assert moved.observations[2] == seen[2]  # not among the frames: left for the fit to report


def test_a_pincushion_lens_leaves_its_empty_rim_out_of_the_mosaic(tmp_path):
    folder = tmp_path / "flight"
    make_flight(folder, SMALL, seed=4)
    pincushion = Lens(320, 240, 0.8, 0.8, k1=0.25)
    valid = pincushion.valid_mask((320, 240))
    assert valid[120, 160] == 1 and valid[0, 0] == 0 and valid[0, 160] == 0  # its rim falls outside its field
    assert 0.01 < 1 - valid.mean() < 0.2
    assert Lens(320, 240, 0.8, 0.8, k1=-0.15).valid_mask((320, 240)).all()  # a barrel lens fills the frame
    cameras = write_cameras(tmp_path / "cameras.json", cam={**BARREL, "k1": 0.25, "k2": 0.0, "c_x": 0.0, "c_y": 0.0})
    report = run_mosaic(folder, tmp_path / "m.png", MosaicConfig(method="sift"), camera=cameras)
    mosaic = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED)
    # Every frame's corner pixel is empty in the mosaic unless another frame's real pixels cover it; the
    # outermost corners of the flight are covered by one frame only.
    first = next(f for f in report["frames"] if f["index"] == 0)
    corner = cv2.perspectiveTransform(np.array([[[1.0, 1.0]]]), np.array(first["mosaic_from_frame"]))[0, 0]
    x, y = int(round(corner[0])), int(round(corner[1]))
    assert mosaic[y, x, 3] == 0
    inside = cv2.perspectiveTransform(np.array([[[160.0, 120.0]]]), np.array(first["mosaic_from_frame"]))[0, 0]
    assert mosaic[int(round(inside[1])), int(round(inside[0])), 3] == 255
