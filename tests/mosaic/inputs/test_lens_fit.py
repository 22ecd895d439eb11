"""One k1 for a flight, fitted from its own matches: none for a pinhole camera, the lens's for a barrel one."""

from __future__ import annotations

import cv2
import pytest

from udh_cli.errors import UdhError
from udh_cli.images import to_gray_u8
from udh_cli.mosaic import MosaicConfig, run_mosaic
from udh_cli.mosaic.inputs.lens import Lens
from udh_cli.mosaic.inputs.lens_fit import DEFAULT_FOCAL, fit_k1, focal_from_exif
from udh_cli.simulate import FlightConfig

from mosaic_flights import SMALL, distort, make_flight

BARREL = Lens(320, 240, 0.8, 0.8, 0.01, -0.01, k1=-0.15, k2=0.02)  # 18 px at the corners
FLIGHT = FlightConfig(frame_size=(320, 240), strips=3, frames_per_strip=6, focal_px=300.0)


@pytest.fixture(scope="module")
def greys(tmp_path_factory):
    paths = make_flight(tmp_path_factory.mktemp("k1"), FLIGHT, seed=4)
    images = [cv2.imread(str(p)) for p in paths]
    return [to_gray_u8(i) for i in images], [to_gray_u8(distort(i, BARREL)) for i in images]


def test_a_pinhole_flight_gets_no_lens(greys):
    pinhole, _ = greys
    fit = fit_k1(pinhole, 0.8)
    assert fit.k1 == 0.0 and fit.rms_with_px == fit.rms_without_px < 0.6 and fit.pairs >= 10


def test_a_barrel_lens_is_found_and_its_k1_trades_with_the_focal_length(greys):
    _, barrel = greys
    fit = fit_k1(barrel, 0.8)
    # Measured: k1 -0.136 with the true focal length (the lens's k2 of +0.02 is folded into one k1), and the
    # matches' homography residual 0.83 -> 0.53 px RMS, close to the pinhole frames' 0.42.
    assert -0.17 < fit.k1 < -0.11 and fit.rms_with_px < 0.75 * fit.rms_without_px
    shorter = fit_k1(barrel, 0.7)
    assert shorter.k1 == pytest.approx(fit.k1 * (0.7 / 0.8) ** 2, abs=0.01)  # the same bend in pixels
    assert shorter.rms_with_px == pytest.approx(fit.rms_with_px, abs=0.02)


def test_the_focal_length_comes_from_exif_when_it_is_there():
    assert focal_from_exif(24.0) == (pytest.approx(24 / 36), "EXIF 35 mm equivalent")
    assert focal_from_exif(None)[0] == focal_from_exif(2000.0)[0] == DEFAULT_FOCAL  # absent or absurd: the default


def test_too_few_matching_pairs_is_a_clear_error(greys):
    pinhole, _ = greys
    flat = [pinhole[0] * 0 + 128] * 4
    with pytest.raises(UdhError, match="give the camera's cameras.json"):
        fit_k1(flat, 0.8)


def test_a_distorted_flight_mosaics_to_its_truth_with_the_estimated_lens(tmp_path):
    folder = tmp_path / "flight"
    paths = make_flight(folder, SMALL, seed=4)
    for path in paths:
        cv2.imwrite(str(path), distort(cv2.imread(str(path)), BARREL), [cv2.IMWRITE_JPEG_QUALITY, 95])
    config = MosaicConfig(method="sift")
    plain = run_mosaic(folder, tmp_path / "plain.png", config)
    fitted = run_mosaic(folder, tmp_path / "fitted.png", config, camera="estimate")
    error = lambda report: report["ground_truth_error"]["solved"]["mean_corner_px"]  # noqa: E731
    estimated = fitted["camera"]["estimated"]
    assert fitted["camera"]["k1"] == pytest.approx(estimated["k1"], abs=1e-5) and estimated["k1"] < -0.05
    assert estimated["focal_source"].startswith("assumed")
    # Measured: 21.4 px without a lens, 3.2 px with the fitted k1 (-0.100 at the assumed focal length 0.7), 0.81 px
    # with the true camera (test_lens.py): one k1 cannot hold the lens's k2 and its off-centre principal point.
    assert error(fitted) < 4.0 and error(plain) > 10.0


def test_the_kept_decodes_are_undistorted_by_the_fitted_lens_as_a_second_read_is(tmp_path):
    import numpy as np

    from udh_cli.mosaic import Reporter
    from udh_cli.mosaic.inputs.frames import open_frames
    from udh_cli.mosaic.inputs.lens_fit import undistort_by_fitted_lens

    paths = make_flight(tmp_path, SMALL, seed=4)
    for path in paths:
        cv2.imwrite(str(path), distort(cv2.imread(str(path)), BARREL))
    frames = open_frames(tmp_path, 320, keep_decoded_bytes=2**30)
    assert undistort_by_fitted_lens(frames, Reporter(quiet=True)).k1 < -0.05
    kept = frames.take_decoded([0, 5])
    read_again = dict(frames.full_images([0, 5]))
    assert sorted(kept) == [0, 5] and all(np.array_equal(kept[i], read_again[i]) for i in kept)
