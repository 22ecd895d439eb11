"""Exposure compensation with OpenCV's compensators on a part drawn small."""

from __future__ import annotations

import numpy as np
import pytest

from udh_cli.errors import UdhError
from udh_cli.mosaic.render.gains import apply_gain, exposure_gains, mean_gain
from udh_cli.mosaic.render.small import SmallPart, small_scale

from conftest import textured_image


def overlapping_part(colour_b=(1.0, 1.0, 1.0), shift=60) -> SmallPart:
    """Two 160x120 views of one colour scene, B ``shift`` px to the right of A and its channels scaled."""
    grey = textured_image(160 + shift, 120, seed=3).astype(np.float64)
    scene = np.stack([grey * 0.9, grey, grey * 0.8], axis=2)
    a = scene[:, :160]
    b = np.clip(scene[:, shift:] * np.array(colour_b), 0, 255)
    mask = np.full((120, 160), 255, np.uint8)
    return SmallPart(1.0, [0, 1], [(0, 0), (shift, 0)], [a.astype(np.uint8), b.astype(np.uint8)], [mask, mask.copy()])


@pytest.mark.parametrize("kind", ["gain", "channels", "blocks"])
def test_equal_frames_keep_gains_of_one(kind):
    gains = exposure_gains(kind, overlapping_part())
    for gain in gains.values():
        np.testing.assert_allclose(mean_gain(gain), [1.0, 1.0, 1.0], atol=0.02)


def test_channel_gains_undo_a_white_balance_shift_that_one_gain_cannot():
    part = overlapping_part(colour_b=(0.8, 1.0, 1.2))
    channels = exposure_gains("channels", part)
    # B's channels times its gains against A's times A's: the prior that keeps gains near 1 (OpenCV's, Brown &
    # Lowe's) leaves part of the difference, but far less than there was.
    ratio = np.array(mean_gain(channels[1])) / np.array(mean_gain(channels[0]))
    left = np.abs(np.array([0.8, 1.0, 1.2]) * ratio - 1.0)
    assert left[0] < 0.5 * 0.2 and left[2] < 0.5 * 0.2 and left[1] < 0.01
    single = exposure_gains("gain", part)
    one = np.array(mean_gain(single[1])) / np.array(mean_gain(single[0]))
    assert abs(one[0] - one[2]) < 1e-9  # one multiplier for every channel


def test_a_gain_map_is_stretched_over_the_warped_box():
    warped = np.full((40, 60, 3), 100.0, np.float32)
    gain_map = np.ones((2, 3, 3))
    gain_map[:, 2] = 1.5  # the right third of the frame is brightened
    out = apply_gain(warped, gain_map)
    assert out.shape == warped.shape
    assert out[20, 2, 0] == pytest.approx(100.0) and out[20, 58, 0] == pytest.approx(150.0)
    np.testing.assert_allclose(apply_gain(warped, np.array([1.0, 2.0, 0.5]))[0, 0], [100.0, 200.0, 50.0])


def test_none_and_unknown_kinds():
    part = overlapping_part()
    assert all(np.array_equal(g, np.ones(3)) for g in exposure_gains("none", part).values())
    with pytest.raises(UdhError, match="exposure"):
        exposure_gains("sepia", part)


def test_small_copies_hold_about_a_tenth_of_a_megapixel_per_frame_within_a_budget():
    assert small_scale([(1600, 1200)] * 10, 1.0) == pytest.approx((0.1e6 / (1600 * 1200)) ** 0.5)
    assert small_scale([(320, 240)] * 3, 1.0) == 1.0  # never enlarged
    many = small_scale([(1600, 1200)] * 2000, 1.0)
    assert 2000 * 1600 * 1200 * many**2 == pytest.approx(10e6)
