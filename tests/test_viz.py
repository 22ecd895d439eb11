"""The figure-1 style picture: A's border warped onto B, drawn where it belongs and nowhere else."""

from __future__ import annotations

import numpy as np

from udh_cli import geometry
from udh_cli.viz import ESTIMATE_COLOUR, TRUTH_COLOUR, draw_estimate


def colour_mask(picture: np.ndarray, colour) -> np.ndarray:
    return np.all(np.abs(picture.astype(int) - np.array(colour)) < 40, axis=-1)


def test_layout_and_where_lines_go():
    grey = np.full((100, 150), 128, np.uint8)
    shift = geometry.translation(20.0, 10.0)
    picture = draw_estimate(grey, grey, shift, np.eye(3), label="sift")
    assert picture.dtype == np.uint8 and picture.ndim == 3
    assert picture.shape[1] == 150 + 12 + 150 and picture.shape[0] > 100  # side by side, caption below
    green, red = colour_mask(picture, ESTIMATE_COLOUR), colour_mask(picture, TRUTH_COLOUR)
    # The estimate's border: its left edge at x = 20 in B, which starts at column 162.
    assert green[40:90, 162 + 20].all() and not green[:, :162].any()
    # The truth (identity) lies along B's own border; nothing is drawn over A or the caption.
    assert red[20:80, 162].all() and not red[:, :162].any() and not red[100:].any()


def test_lines_leaving_b_are_clipped_to_b():
    grey = np.full((100, 150), 128, np.uint8)
    far_left = geometry.translation(-120.0, 30.0)  # most of A's border lands left of B
    picture = draw_estimate(grey, grey, far_left)
    assert colour_mask(picture, ESTIMATE_COLOUR)[:, 162:].any()
    assert not colour_mask(picture, ESTIMATE_COLOUR)[:, :162].any()


def test_extreme_homography_does_not_crash_and_large_images_are_scaled():
    big = np.zeros((900, 1600, 3), np.uint8)
    wild = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1e-3, 0.0, 1.0]])  # the horizon crosses A at x = 1000
    picture = draw_estimate(big, big, wild, max_width=800)
    assert picture.shape[1] <= 800
    at_infinity = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0 / 1599, 0.0, -1.0]])  # w = 0 at a corner
    draw_estimate(big, big, at_infinity, max_width=800)
    deep = np.zeros((50, 60), np.uint16)
    assert draw_estimate(deep, deep, None, label="ecc").shape[2] == 3
