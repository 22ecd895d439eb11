"""The known motions of `udh bench hard`: each kind draws what it says, and the truth is the motion composed with
the reference, checked on images the test makes (exact pixels where the motion maps pixels onto pixels)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.bench.motions import MOTION_KINDS, Motion, draw_motion, fits, move_pair, overlap

from conftest import textured_image

SHIFT = (7.0, -5.0)  # the reference: B is A shifted by whole pixels, so it is exact


def shifted_pair(side: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A square textured A, B = A moved by SHIFT (whole pixels) and the exact ``b_from_a``."""
    source = textured_image(side + 40, side + 40, seed=3)
    dx, dy = int(SHIFT[0]), int(SHIFT[1])
    image_a = source[20 : 20 + side, 20 : 20 + side].copy()
    image_b = source[20 - dy : 20 - dy + side, 20 - dx : 20 - dx + side].copy()
    return image_a, image_b, geometry.translation(*SHIFT)


def test_the_reference_of_the_test_pair_is_exact():
    image_a, image_b, b_from_a = shifted_pair()
    # Pixel (x, y) of A is pixel (x + 7, y - 5) of B.
    np.testing.assert_array_equal(image_b[10 - 5 : 50 - 5, 10 + 7 : 50 + 7], image_a[10:50, 10:50])


def test_a_quarter_turn_moves_every_pixel_where_the_composed_truth_says():
    image_a, image_b, b_from_a = shifted_pair()
    side = image_b.shape[0]
    motion = Motion("in-plane rotation", turn=90.0).homography((side, side))
    moved, truth = move_pair(image_b, b_from_a, motion)
    np.testing.assert_array_equal(moved, np.rot90(image_b, k=-1))  # a quarter turn clockwise on screen
    # Exact arithmetic: A's (x, y) is B's (x + 7, y - 5), which the turn sends to (side - 1 - (y - 5), x + 7).
    corners = geometry.image_corners(side, side)
    expected = np.stack([side - 1 - (corners[:, 1] - 5), corners[:, 0] + 7], 1)
    np.testing.assert_allclose(geometry.transform_points(truth, corners), expected, atol=1e-9)
    ys, xs = np.mgrid[10:40, 10:40]
    xb, yb = geometry.transform_points(truth, np.stack([xs.ravel(), ys.ravel()], 1).astype(float)).round().astype(int).T
    np.testing.assert_array_equal(moved[yb, xb], image_a[ys.ravel(), xs.ravel()])


def test_doubling_about_the_centre_is_composed_after_the_reference():
    _, image_b, b_from_a = shifted_pair(side=97)  # odd: the centre is a pixel, so x -> 2x - 48 lands on pixels
    motion = Motion("scale", scale=2.0).homography((97, 97))
    _, truth = move_pair(image_b, b_from_a, motion)
    point = np.array([[30.0, 40.0]])  # in A: B's (37, 35), then 2 (p - 48) + 48
    np.testing.assert_allclose(geometry.transform_points(truth, point), [[2 * 37 - 48, 2 * 35 - 48]], atol=1e-9)


@pytest.mark.parametrize("kind", MOTION_KINDS)
def test_every_kind_sends_a_blob_of_A_where_the_truth_says(kind):
    """A bright blob at a known point of A ends up, after the reference and the drawn motion, where the truth maps it."""
    side = 200
    image_a = np.zeros((side, side), np.uint8)
    cv2.circle(image_a, (100, 100), 3, 255, -1)
    image_a = cv2.GaussianBlur(image_a, (0, 0), 1.0)
    image_b = np.zeros_like(image_a)
    image_b[:, 7:] = image_a[:, :-7]  # B = A shifted 7 px right
    b_from_a = geometry.translation(7.0, 0.0)
    rng = np.random.default_rng(4)
    for _ in range(5):
        motion = draw_motion(kind, rng)
        moved, truth = move_pair(image_b, b_from_a, motion.homography((side, side)))
        expected = geometry.transform_points(truth, np.array([[100.0, 100.0]]))[0]
        if not (10 < expected[0] < side - 10 and 10 < expected[1] < side - 10):
            continue  # the motion sent the blob off B
        ys, xs = np.mgrid[0:side, 0:side]
        weights = moved.astype(np.float64)
        centroid = np.array([(xs * weights).sum(), (ys * weights).sum()]) / weights.sum()
        np.testing.assert_allclose(centroid, expected, atol=0.5)  # a shrunk or tilted blob shifts its centroid a little


def test_each_kind_draws_its_own_range():
    rng = np.random.default_rng(0)
    draws = {kind: [draw_motion(kind, rng) for _ in range(300)] for kind in MOTION_KINDS}
    turns = np.array([m.turn for m in draws["in-plane rotation"]])
    assert turns.min() < 10 and turns.max() > 350 and np.histogram(turns, bins=4, range=(0, 360))[0].min() > 50
    assert all(m.scale == 1 and m.tilt == 0 for m in draws["in-plane rotation"])
    scales = np.array([m.scale for m in draws["scale"]])
    assert np.all((scales >= 2**0.4 - 1e-9) | (scales <= 2**-0.4 + 1e-9)) and scales.max() <= 2 and scales.min() >= 0.5
    assert (scales > 1).mean() == pytest.approx(0.5, abs=0.1)
    yaw = [m.homography((800, 600)) for m in draws["vertical-axis rotation"]]
    # About a vertical axis: the perspective row varies with x only, and strongly.
    assert all(abs(h[2, 1]) < 1e-15 and abs(h[2, 0]) > 3e-4 for h in yaw)
    extreme = draws["extreme viewpoint and scale"]
    assert all(35 <= m.tilt <= 55 and (m.scale >= 1.5 or m.scale <= 1 / 1.5) for m in extreme)
    mixed = draws["mixed"]
    assert np.ptp([m.turn for m in mixed]) > 300 and max(m.tilt for m in mixed) > 25 and np.ptp([m.scale for m in mixed]) > 0.6


def test_draws_are_reproducible_from_the_seed():
    first = [draw_motion(k, np.random.default_rng(9)) for k in MOTION_KINDS]
    assert first == [draw_motion(k, np.random.default_rng(9)) for k in MOTION_KINDS]


def test_overlap_and_fit():
    assert overlap(np.eye(3), (100, 80), (100, 80)) == 1.0
    assert overlap(geometry.translation(50.0, 0.0), (100, 80), (100, 80)) == pytest.approx(0.5, abs=0.05)
    assert overlap(geometry.translation(200.0, 0.0), (100, 80), (100, 80)) == 0.0
    assert fits(np.eye(3), (100, 80), (100, 80)) and not fits(geometry.translation(90.0, 0.0), (100, 80), (100, 80))
    horizon = np.array([[1.0, 0, 0], [0, 1, 0], [-0.02, 0, 1]])  # w = 0 at x = 50: inside A
    assert not fits(horizon, (100, 80), (100, 80))
    # Valid and overlapping, but a corner of A flung 10 frames away (near the horizon): not scored.
    near_horizon = np.array([[1.0, 0, 0], [0, 1, 0], [-0.7 / 99, 0, 1]])  # w = 0.3 at A's right edge: x 99 -> 330
    assert geometry.is_valid_homography(near_horizon, 100, 80) and overlap(near_horizon, (100, 80), (100, 80)) > 0.25
    assert not fits(near_horizon, (100, 80), (100, 80))
