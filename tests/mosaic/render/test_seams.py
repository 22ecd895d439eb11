"""Seams with OpenCV's seam finders: around what differs between frames, and drawn back at full resolution."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from udh_cli.errors import UdhError
from udh_cli.mosaic.render.seams import Seams, find_seams
from udh_cli.mosaic.render.small import SmallPart

from conftest import textured_image


def part_with_a_blob_in_a(shift: int = 80) -> SmallPart:
    """A and B: 160x120 views of one scene, B ``shift`` px right of A; A shows a bright blob (a hot spot, a
    car) in the overlap's upper half, at canvas x 110-140, y 15-45, that B does not."""
    grey = textured_image(160 + shift, 120, seed=5)
    scene = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    a, b = scene[:, :160].copy(), scene[:, shift:].copy()
    cv2.circle(a, (125, 30), 15, (250, 250, 250), -1)
    mask = np.full((120, 160), 255, np.uint8)
    return SmallPart(1.0, [0, 1], [(0, 0), (shift, 0)], [a, b], [mask, mask.copy()])


@pytest.mark.parametrize("kind", ["dp", "graphcut"])
def test_the_seam_leaves_what_only_one_frame_shows_to_the_other(kind):
    seams = find_seams(kind, part_with_a_blob_in_a())
    a_shows, b_shows = seams.masks[0] > 0, seams.masks[1] > 0
    assert not a_shows[30, 125]  # the blob's centre, in A's pixels: B shows it
    assert b_shows[30, 125 - 80]
    # Every covered pixel is shown by at least one frame, and the overlap mostly by one only.
    canvas_a = np.zeros((120, 240), bool)
    canvas_b = np.zeros((120, 240), bool)
    canvas_a[:, :160], canvas_b[:, 80:] = a_shows, b_shows
    assert (canvas_a | canvas_b).mean() > 0.99
    assert (canvas_a & canvas_b).mean() < 0.05


def test_central_needs_no_search_and_unknown_kinds_are_refused():
    assert find_seams("central", part_with_a_blob_in_a()) is None
    with pytest.raises(UdhError, match="seam"):
        find_seams("voronoi-ish", part_with_a_blob_in_a())


def test_a_small_seam_mask_is_drawn_exactly_over_a_full_resolution_box():
    mask = np.zeros((30, 40), np.uint8)
    mask[10:20, 5:15] = 255  # small-canvas x 25-34, y 20-29 (the mask sits at corner (20, 10))
    seams = Seams({7: mask}, {7: (20, 10)}, scale=0.25)
    drawn = seams.in_box(7, (80, 60, 160, 140))  # canvas x 80-159 -> small x 20-39.75
    assert drawn.shape == (80, 80)
    ys, xs = np.nonzero(drawn)
    # small x 25 -> canvas 100 (box column 20), small x 35 -> canvas 140; y likewise from 80 (box row 20) to 120:
    # exact to within the rounding of one small pixel (4 canvas pixels)
    np.testing.assert_allclose([xs.min(), xs.max() + 1, ys.min(), ys.max() + 1], [20, 60, 20, 60], atol=2)
    assert drawn.sum() == pytest.approx(40 * 40, rel=0.1)
