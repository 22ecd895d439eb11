"""The flight-motion generator: labels that match the pixels, and the motion it promises."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from conftest import textured_image
from udh_cli import geometry
from udh_cli.flight_motion import MotionConfig, flight_lighting, make_motion_pairs, similarity_about, source_size


@pytest.fixture(scope="module")
def sources() -> list[np.ndarray]:
    return [cv2.resize(textured_image(640, 480, seed=s), source_size(640, 480)) for s in range(4)]


def _heading_and_scale(b_from_a: np.ndarray, patch: int) -> tuple[float, float]:
    """Rotation (degrees) and scale of the view homography at the view centre. The views squash the frame's
    width, so this is exact only for square frames; the test keeps to those where it checks angles."""
    c = np.array([[(patch - 1) / 2, (patch - 1) / 2]])
    centre = geometry.transform_points(b_from_a, c)[0]
    dx = geometry.transform_points(b_from_a, c + [1.0, 0.0])[0] - centre
    dy = geometry.transform_points(b_from_a, c + [0.0, 1.0])[0] - centre
    return math.degrees(math.atan2(dx[1], dx[0])), math.sqrt(abs(dx[0] * dy[1] - dx[1] * dy[0]))


def test_the_offsets_align_the_clean_views(sources):
    batch = make_motion_pairs(sources, 24, MotionConfig(lighting=0.0), np.random.default_rng(0), patch=128, illumination=False)
    homographies = batch.homographies()
    for i in range(24):
        clean_a = batch.context_a[i, 0, 128:256, 128:256]
        assert np.abs(clean_a - batch.patch_a[i]).mean() < 2e-3  # context holds A's view at (P, P), to OpenCV's warp rounding
        warped = cv2.warpPerspective(clean_a, homographies[i], (128, 128), flags=cv2.INTER_LINEAR)
        covered = cv2.warpPerspective(np.ones_like(clean_a), homographies[i], (128, 128)) > 0.999
        assert covered.mean() >= 0.3 - 0.02  # the promised overlap (tiles at the border round it slightly)
        assert np.abs(warped - batch.clean_b[i])[covered].mean() < 0.03


def test_residual_pairs_show_a_prewarped_a_and_label_what_is_left(sources):
    config = MotionConfig(lighting=0.0, residual=10.0)
    batch = make_motion_pairs(sources, 24, config, np.random.default_rng(2), patch=128, illumination=False)
    assert np.abs(batch.offsets).max() <= 10.0 + 1e-4  # the label is the residual, not the flight motion
    assert np.abs(batch.offsets).mean() > 2.0
    homographies = batch.homographies()
    reflected = 0
    for i in range(24):
        # The context is the source in the pre-warped A's frame: the residual label aligns it with B.
        warped = cv2.warpPerspective(batch.context_a[i, 0], homographies[i] @ geometry.translation(-128, -128), (128, 128))
        assert np.abs(warped - batch.clean_b[i]).mean() < 0.03
        # Outside A's own frame the network sees the border fill (PREWARP_BORDER), as the cascade's rounds do,
        # so that part of its view differs from the true surroundings in the context.
        seen = batch.patch_a[i]
        truly = batch.context_a[i, 0, 128:256, 128:256]
        reflected += float(np.abs(seen - truly).mean() > 0.01)
    assert reflected >= 12  # most pairs overlap by less than the whole view
    assert config.scaled(0.5).residual == 10.0  # small-motion pairs shrink the motion, not the residual


def test_motion_reaches_its_ranges_and_no_further(sources):
    config = MotionConfig(max_heading=60.0, scale_range=(0.8, 1.25), max_shift=0.3, perspective=0.0, lighting=0.0)
    batch = make_motion_pairs(sources, 200, config, np.random.default_rng(1), patch=64, illumination=False, with_context=False)
    offsets = np.abs(batch.offsets).max((1, 2))
    assert offsets.max() > 30  # large motion, far beyond the paper's rho
    # Angles and scales hold in the isotropic frame; views squash non-square frames, so check the square ones.
    found = [_heading_and_scale(h, 64) for h in batch.homographies()]
    headings = np.abs([f[0] for f in found])
    assert headings.max() < 60.0 * 1.9 and np.percentile(headings, 50) > 5  # within the range, spread over it


def test_scaled_motion_shrinks_everything_and_zero_is_still_a_valid_pair(sources):
    config = MotionConfig()
    assert config.scaled(0.0).max_heading == 0.0 and config.scaled(0.0).scale_range == (1.0, 1.0)
    small = make_motion_pairs(sources, 50, config, np.random.default_rng(2), patch=64, small_motion_fraction=1.0,
                              illumination=False, with_context=False)
    full = make_motion_pairs(sources, 50, config, np.random.default_rng(2), patch=64, illumination=False, with_context=False)
    assert np.median(np.abs(small.offsets)) < np.median(np.abs(full.offsets))


def test_same_seed_same_pairs(sources):
    a = make_motion_pairs(sources, 6, MotionConfig(), np.random.default_rng(5), patch=64)
    b = make_motion_pairs(sources, 6, MotionConfig(), np.random.default_rng(5), patch=64)
    assert np.array_equal(a.patch_a, b.patch_a) and np.array_equal(a.offsets, b.offsets)


def test_lighting_effects_stay_in_range_and_change_the_view():
    view = textured_image(64, 64).astype(np.float32) / 255.0
    lit = flight_lighting(view, np.random.default_rng(3), probability=1.0)
    assert lit.shape == view.shape and lit.dtype == np.float32
    assert 0.0 <= lit.min() and lit.max() <= 1.0
    assert np.abs(lit - view).mean() > 0.01
    assert np.array_equal(flight_lighting(view, np.random.default_rng(3), probability=0.0), view)


def test_similarity_about_keeps_its_centre_and_turns_by_the_angle():
    h = similarity_about((10.0, 20.0), 90.0, 2.0, (0.0, 0.0))
    np.testing.assert_allclose(geometry.transform_points(h, np.array([[10.0, 20.0]])), [[10.0, 20.0]], atol=1e-9)
    np.testing.assert_allclose(geometry.transform_points(h, np.array([[11.0, 20.0]])), [[10.0, 22.0]], atol=1e-9)


def test_source_size_keeps_room_for_large_motion():
    assert source_size(1600, 900) == (640, 360)
    assert source_size(400, 400) == (360, 360)
    assert source_size(300, 1200) == (360, 720)  # aspect capped at 2
