"""Seams with OpenCV's seam finders: around what differs between frames, and drawn back at full resolution."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from udh_cli.errors import UdhError
from udh_cli.mosaic.render.seams import Seams, dp_seam_masks, find_seams
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


def part_with_passers_by(count: int = 6) -> SmallPart:
    """``count`` 160x120 colour views of one 420x260 scene at irregular offsets (no two pairs of centres
    equally far apart), each with discs (cars, people) that only it shows, so the seams have something to avoid."""
    rng = np.random.default_rng(11)
    scene = np.dstack([textured_image(420, 260, seed=s) for s in (1, 2, 3)])
    offsets = [(0, 0), (97, 13), (190, 5), (31, 101), (128, 117), (233, 96), (260, 140), (60, 139)][:count]
    images = []
    for x, y in offsets:
        view = scene[y : y + 120, x : x + 160].copy()
        for _ in range(6):
            centre = (int(rng.integers(0, 160)), int(rng.integers(0, 120)))
            cv2.circle(view, centre, int(rng.integers(6, 16)), tuple(int(v) for v in rng.integers(0, 256, 3)), -1)
        images.append(view)
    masks = [np.full((120, 160), 255, np.uint8) for _ in offsets]
    return SmallPart(1.0, list(range(count)), offsets, images, masks)


def opencv_dp_masks(part: SmallPart) -> list[np.ndarray]:
    finder = cv2.detail_DpSeamFinder("COLOR")
    found = finder.find([cv2.UMat(image.astype(np.float32)) for image in part.images], part.corners, [cv2.UMat(m) for m in part.masks])
    return [mask.get() for mask in found]


def owners(part: SmallPart, masks: list[np.ndarray]) -> np.ndarray:
    """(H, W) int: the first frame whose seam mask shows each small-canvas pixel, -1 where none does."""
    width = max(x + image.shape[1] for (x, _), image in zip(part.corners, part.images))
    height = max(y + image.shape[0] for (_, y), image in zip(part.corners, part.images))
    owner = np.full((height, width), -1)
    for k in reversed(range(len(masks))):
        x, y = part.corners[k]
        h, w = masks[k].shape
        owner[y : y + h, x : x + w][masks[k] > 0] = k
    return owner


def seam_cost(part: SmallPart, owner: np.ndarray) -> tuple[int, float]:
    """Seam pixels (neighbours with different owners) and the mean absolute colour difference, in grey levels,
    of the two frames there: what a seam finder minimises."""
    def colour(k, ys, xs):
        x, y = part.corners[k]
        return part.images[k][ys - y, xs - x].astype(np.float32)

    differences = []
    for dy, dx in ((0, 1), (1, 0)):
        a, b = owner[: owner.shape[0] - dy, : owner.shape[1] - dx], owner[dy:, dx:]
        ys, xs = np.nonzero((a != b) & (a >= 0) & (b >= 0))
        for ka, kb in set(zip(a[ys, xs], b[ys, xs])):
            pick = (a[ys, xs] == ka) & (b[ys, xs] == kb)
            py, px = ys[pick], xs[pick]
            differences.append(np.abs(colour(ka, py, px) - colour(kb, py, px)).mean(1))
    differences = np.concatenate(differences)
    return differences.size, float(differences.mean())


def test_dp_on_whole_frames_is_opencvs_finder_pair_by_pair():
    part = part_with_passers_by()
    whole = dp_seam_masks(part.images, part.corners, part.masks, margin=10**6)
    for ours, theirs in zip(whole, opencv_dp_masks(part)):
        np.testing.assert_array_equal(ours, theirs)


def test_two_threads_find_the_same_seams_as_one():
    part = part_with_passers_by(8)
    one, two = find_seams("dp", part, workers=1), find_seams("dp", part, workers=2)
    for k in part.indices:
        np.testing.assert_array_equal(one.masks[k], two.masks[k])


def test_the_window_around_each_overlap_keeps_the_finders_seams():
    part = part_with_passers_by(8)
    theirs = owners(part, opencv_dp_masks(part))
    ours = owners(part, list(find_seams("dp", part).masks.values()))
    np.testing.assert_array_equal(ours >= 0, theirs >= 0)  # every pixel some frame covers is still shown
    overlap = sum((owners(part, [m if i == k else 0 * m for i, m in enumerate(part.masks)]) >= 0).astype(int)
                  for k in range(len(part.masks))) > 1
    assert (ours == theirs)[overlap].mean() > 0.95  # the same frame shown over nearly all of the overlaps
    (our_length, our_cost), (their_length, their_cost) = seam_cost(part, ours), seam_cost(part, theirs)
    assert our_length == pytest.approx(their_length, rel=0.1)
    assert our_cost <= their_cost * 1.05  # and seams through places where the frames agree as well as the finder's
    # A frame keeps every pixel it alone covers: only overlaps are decided.
    for k, mask in find_seams("dp", part).masks.items():
        x, y = part.corners[k]
        alone = ~overlap[y : y + 120, x : x + 160]
        assert (mask[alone] == 255).all()
