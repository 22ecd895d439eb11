"""Global matching of dense descriptors (udh_cli.estimators.matching), with hand-made descriptors."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import BlockDescriptors, textured_image
from udh_cli import geometry
from udh_cli.estimators import matching
from udh_cli.estimators.pair import PreparedImage


def test_cell_centres_follow_the_pixel_centre_convention():
    centres = matching.cell_centres(2, 3)
    assert centres.shape == (6, 2)
    np.testing.assert_allclose(centres[0], [1.5, 1.5])  # cell 0 covers pixels 0..3
    np.testing.assert_allclose(centres[5], [9.5, 5.5])  # row-major: (x 2, y 1)


def _unit(features: np.ndarray) -> np.ndarray:
    return (features / (np.linalg.norm(features, axis=0, keepdims=True) + 1e-9)).astype(np.float32)


def test_mutual_matches_find_a_shift_of_whole_cells():
    rng = np.random.default_rng(0)
    scene = _unit(rng.normal(size=(16, 20, 30)))
    features_a, features_b = scene[:, 2:14, 3:23], scene[:, 5:17, 1:21]  # A's cell (x, y) is B's (x + 2, y - 3)
    points_a, points_b, similarity = matching.mutual_matches(features_a, features_b)
    exact = similarity > 0.9999
    assert exact.sum() == 9 * 18  # every cell of the shared rows 5..13 and columns 3..20 of the scene
    # The right cell every time; the sub-cell placement moves a match by at most half a cell (random
    # descriptors have no smooth peak to place it by).
    assert np.abs(points_b[exact] - points_a[exact] - [8.0, -12.0]).max() <= 2.0 + 1e-6
    assert similarity[~exact].max() < 0.9  # the rest are chance pairs among cells only one side sees


def test_a_cell_whose_best_match_prefers_another_cell_is_not_mutual():
    # Two A cells both nearest to B's cell 0; only the more similar one (A's cell 1) is its mutual match.
    b = _unit(np.eye(4, dtype=np.float32).reshape(4, 1, 4) + 0.0)  # B: 1 x 4 grid of one-hot descriptors
    a = np.zeros((4, 1, 2), np.float32)
    a[:, 0, 0] = [0.8, 0.6, 0.0, 0.0]  # cosine 0.8 with B's cell 0, 0.6 with cell 1
    a[:, 0, 1] = [0.9, 0.0, 0.0, 0.436]  # cosine 0.9 with B's cell 0
    points_a, points_b, similarity = matching.mutual_matches(_unit(a), b, ratio=1.0)
    assert len(points_a) == 1
    np.testing.assert_allclose(points_a[0], [5.5, 1.5])  # A's cell 1
    np.testing.assert_allclose(similarity, [0.9], atol=1e-3)


def test_cells_that_tie_for_a_match_give_one_match():
    # A's cells 0 and 1 are the same descriptor, both nearest B's cell 0: one match, from the first.
    b = _unit(np.eye(4, dtype=np.float32).reshape(4, 1, 4))
    a = np.zeros((4, 1, 2), np.float32)
    a[:, 0, 0] = a[:, 0, 1] = [0.9, 0.0, 0.0, 0.436]
    points_a, _, _ = matching.mutual_matches(_unit(a), b, ratio=1.0)
    np.testing.assert_allclose(points_a, [[1.5, 1.5]])


def test_the_peak_is_placed_between_cells_by_a_parabola():
    # One query against a 1 x 5 grid of 2-d descriptors whose similarity with it is 1 - (x - 2.3)^2 / 20.
    xs = np.arange(5.0)
    similarity = 1.0 - (xs - 2.3) ** 2 / 20
    columns = np.stack([similarity, np.sqrt(1 - similarity**2)], 1)
    query = np.array([[1.0, 0.0]])
    offsets = matching._subcell(query, columns, np.array([2]), 1, 5)
    np.testing.assert_allclose(offsets, [[0.3, 0.0]], atol=1e-6)
    # At the grid's edge there is no neighbour on one side: no offset rather than a guess.
    assert matching._subcell(query, columns, np.array([4]), 1, 5)[0, 0] == 0.0


def test_the_robust_fit_recovers_a_homography_through_outliers_and_refuses_too_few():
    rng = np.random.default_rng(1)
    truth = np.array([[1.05, 0.02, 12.0], [-0.03, 0.98, -7.0], [1e-4, -5e-5, 1.0]])
    points_a = rng.uniform(0, 300, (200, 2))
    points_b = geometry.transform_points(truth, points_a) + rng.normal(0, 0.3, (200, 2))
    points_b[:60] = rng.uniform(0, 300, (60, 2))  # 30 % wrong matches
    found, inliers = matching.fit_matches(points_a, points_b)
    assert found is not None and inliers[60:].mean() > 0.95 and inliers[:60].mean() < 0.1
    assert geometry.mace(found, truth, 320, 240) < 0.5
    assert matching.fit_matches(points_a[:5], points_b[:5])[0] is None


def test_a_global_match_recovers_a_large_shift_and_a_half_turn_in_full_resolution_pixels():
    scene = textured_image(400, 300, seed=3).astype(np.float32) / 255
    a = PreparedImage.of(scene[20:212, 24:280])  # 256 x 192
    shifted = PreparedImage.of(scene[84:276, 120:376])  # B sees A's content moved by (-96, -64): a third of the frame
    found = matching.global_match(BlockDescriptors(), a, shifted, side=256)
    assert found.heading == 0 and found.inliers >= matching.CONFIDENT_INLIERS
    assert geometry.mace(found.b_from_a, geometry.translation(-96, -64), 256, 192) < 0.5
    turned = PreparedImage.of(np.ascontiguousarray(scene[84:276, 120:376][::-1, ::-1]))
    found = matching.global_match(BlockDescriptors(), a, turned, side=256)
    half_turn = np.array([[-1.0, 0, 255], [0, -1.0, 191], [0, 0, 1]])
    assert found.heading == 180
    assert geometry.mace(found.b_from_a, half_turn @ geometry.translation(-96, -64), 256, 192) < 0.5
    # Described at a smaller side, the answer is still in the images' own pixels.
    found = matching.global_match(BlockDescriptors(), a, shifted, side=128)
    assert geometry.mace(found.b_from_a, geometry.translation(-96, -64), 256, 192) < 4.0
    # Descriptors are made once per image and size: the second match of the same frames reuses them.
    assert any(isinstance(key, tuple) and key[0] == "descriptors" for key in a._cache)


def test_a_frame_is_described_once_for_every_pair_it_is_in_and_never_stale():
    class Counting(BlockDescriptors):
        path = "counting blocks"  # its own entries in the process-wide cache

        def __init__(self):
            self.described = 0

        def describe(self, grey):
            self.described += 1
            return super().describe(grey)

    network = Counting()
    scene = textured_image(400, 300, seed=7).astype(np.float32) / 255
    frames = [scene[20 + 24 * k : 212 + 24 * k, 24 + 32 * k : 280 + 32 * k] for k in range(3)]  # whole cells apart
    matching._DESCRIPTORS.clear()
    # As a mosaic does: each pair prepares its images anew, and the middle frame is B, then A.
    for a, b in ((frames[0], frames[1]), (frames[1], frames[2])):
        found = matching.global_match(network, PreparedImage.of(a), PreparedImage.of(b), side=256, headings=1)
        assert geometry.mace(found.b_from_a, geometry.translation(-32, -24), 256, 192) < 0.5
    assert network.described == 3
    changed = frames[2].copy()
    changed[:8] = 0
    matching.global_match(network, PreparedImage.of(frames[1]), PreparedImage.of(changed), side=256, headings=1)
    assert network.described == 4  # new pixels, new descriptors


def test_a_match_too_coarse_to_be_confident_is_tried_again_at_the_larger_side():
    # A sliver of overlap: at 96 px (24 x 18 cells) too few cells are shared to reach the threshold; at 256 px
    # (64 x 48 cells) enough are, and the answer is the finer one.
    scene = textured_image(600, 300, seed=8).astype(np.float32) / 255
    a = PreparedImage.of(scene[40:232, 24:280])
    b = PreparedImage.of(scene[40:232, 216:472])  # A's content moved by 192 px: a quarter of the frame shared
    coarse = matching.global_match(BlockDescriptors(), a, b, side=96, headings=1)
    assert coarse.inliers < matching.CONFIDENT_INLIERS and coarse.side == 96
    escalated = matching.global_match(BlockDescriptors(), a, b, side=96, headings=1, escalate_side=256)
    assert escalated.side == 256 and escalated.inliers >= matching.CONFIDENT_INLIERS
    assert geometry.mace(escalated.b_from_a, geometry.translation(-192, 0), 256, 192) < 0.5
    # Never beyond the frames' own pixels: asked for 768 px, 256-px frames are described at 256.
    assert matching.global_match(BlockDescriptors(), a, b, side=96, headings=1, escalate_side=768).side == 256
    # A confident first match is not tried again.
    whole = PreparedImage.of(scene[40:232, 56:312])
    assert matching.global_match(BlockDescriptors(), a, whole, side=256, headings=1, escalate_side=512).side == 256


def test_unrelated_images_give_no_confident_match():
    a = PreparedImage.of(textured_image(256, 192, seed=4))
    b = PreparedImage.of(textured_image(256, 192, seed=5))
    found = matching.global_match(BlockDescriptors(), a, b, side=256)
    assert found.inliers < matching.CONFIDENT_INLIERS


def test_guided_matching_corrects_an_answer_a_few_pixels_off_within_its_window():
    scene = textured_image(400, 300, seed=6).astype(np.float32) / 255
    a, b = scene[20:212, 24:280], scene[60:252, 80:336]  # B sees A's content moved by (-56, -40)
    features_a, features_b = BlockDescriptors().describe(a), BlockDescriptors().describe(b)
    truth = geometry.translation(-56, -40)
    off = geometry.translation(-56 + 5, -40 - 3)  # a first answer 5 and 3 px off: about a cell
    points_a, points_b = matching.guided_matches(features_a, features_b, off, radius=2)
    assert len(points_a) > 1000
    found, inliers = matching.fit_matches(points_a, points_b, matching.GUIDED_THRESHOLD_PX)
    assert geometry.mace(found, truth, 256, 192) < 1.0 < 5.0 < geometry.mace(off, truth, 256, 192)
    # The refinement runs inside global_match at a larger side and keeps the first match's inliers.
    image_a, image_b = PreparedImage.of(a), PreparedImage.of(b)
    coarse = matching.global_match(BlockDescriptors(), image_a, image_b, side=128)
    refined = matching.global_match(BlockDescriptors(), image_a, image_b, side=128, refine_side=256)
    assert refined.inliers == coarse.inliers
    assert geometry.mace(refined.b_from_a, truth, 256, 192) < 1.0


def test_quarter_turns_are_tried_when_asked_and_undone_exactly():
    scene = textured_image(400, 400, seed=7).astype(np.float32) / 255
    a = PreparedImage.of(scene[40:232, 40:296])  # 256 x 192
    b_view = scene[72:264, 88:344]  # A's content moved by (-48, -32)
    for k in (1, 3):  # B is A's view turned by 90 k degrees; the matcher turns it back by the rest of a turn
        turned = PreparedImage.of(np.ascontiguousarray(np.rot90(b_view, k)))  # 192 x 256
        truth = matching._to_described((256, 192), (256, 192), 90 * k) @ geometry.translation(-48, -32)
        heading = 360 - 90 * k
        assert matching.global_match(BlockDescriptors(), a, turned, side=256).inliers < matching.CONFIDENT_INLIERS
        found = matching.global_match(BlockDescriptors(), a, turned, side=256, headings=4)
        assert found.heading == heading and geometry.mace(found.b_from_a, truth, 256, 192) < 0.5
    # The turn matrix is np.rot90's: a marked pixel lands where the matrix says.
    image = np.zeros((3, 5)); image[1, 4] = 1
    x, y = geometry.transform_points(matching._to_described((5, 3), (5, 3), 90), np.array([[4.0, 1.0]]))[0]
    assert np.rot90(image, 1)[int(round(y)), int(round(x))] == 1


def test_flat_cells_are_left_out_and_a_flat_pair_has_no_match():
    image = np.full((64, 96), 0.5, np.float32)
    image[16:48, 40:80] = textured_image(40, 32, seed=8).astype(np.float32) / 255
    mask = matching.textured_cells(PreparedImage.of(image), (96, 64))
    assert mask.shape == (16, 24)
    assert mask[8, 15] and not mask[1, 1] and not mask[8, 2]  # inside the texture; the flat corner and side
    flat = PreparedImage.of(np.full((192, 256), 0.5, np.float32))
    assert matching.global_match(BlockDescriptors(), flat, flat, side=256).b_from_a is None


def test_a_sliver_of_a_frame_gets_no_match_rather_than_an_error():
    sliver = PreparedImage.of(textured_image(600, 40, seed=9))  # 15:1: 384 x 24 px described, under the matcher's 32
    assert matching.global_match(BlockDescriptors(), sliver, sliver).b_from_a is None


def test_a_quarter_of_the_cells_finds_the_same_matches_for_those_cells():
    scene = textured_image(400, 300, seed=10).astype(np.float32) / 255
    features_a, features_b = BlockDescriptors().describe(scene[20:212, 24:280]), BlockDescriptors().describe(scene[60:252, 80:336])
    whole_a, whole_b, _ = matching.mutual_matches(features_a, features_b)
    quarter = np.zeros(features_a.shape[1:], bool)
    quarter[::2, ::2] = True
    part_a, part_b, _ = matching.mutual_matches(features_a, features_b, rows_a=quarter)
    # Fewer rivals can only add mutual matches: every whole match from a kept cell is among the quarter's, unchanged.
    kept = quarter.ravel()[((whole_a[:, 1] - 1.5) / 4 * features_a.shape[2] + (whole_a[:, 0] - 1.5) / 4).astype(int)]
    found = {tuple(p): tuple(q) for p, q in zip(part_a, part_b)}
    assert kept.sum() > 400 and all(found[tuple(p)] == tuple(q) for p, q in zip(whole_a[kept], whole_b[kept]))
    assert len(part_a) < 0.3 * len(whole_a)


def test_the_second_look_compares_every_cell_only_where_a_quarter_of_them_agree(monkeypatch):
    calls = []
    original = matching.mutual_matches
    monkeypatch.setattr(matching, "mutual_matches", lambda a, b, **kw: calls.append((a.shape[1:], kw.get("rows_a") is not None)) or original(a, b, **kw))
    unrelated = [PreparedImage.of(textured_image(256, 192, seed=s)) for s in (4, 5)]
    found = matching.global_match(BlockDescriptors(), *unrelated, side=96, headings=2, escalate_side=256)
    assert found.inliers < matching.SCREEN_INLIERS and found.side == 96
    assert [c for c in calls if c[0] == (48, 64)] == [((48, 64), True)] * 2  # a quarter look at each heading, no whole one
    calls.clear()
    scene = textured_image(600, 300, seed=8).astype(np.float32) / 255
    sliver = [PreparedImage.of(scene[40:232, 24:280]), PreparedImage.of(scene[40:232, 216:472])]
    assert matching.global_match(BlockDescriptors(), *sliver, side=96, headings=1, escalate_side=256).side == 256
    assert [c for c in calls if c[0] == (48, 64)] == [((48, 64), True), ((48, 64), False)]


def test_one_record_checks_the_global_match_settings_of_every_estimator():
    from udh_cli.errors import UdhError

    assert matching.MatchSettings().checked("matcher") == matching.MatchSettings()
    with pytest.raises(UdhError, match=r"^method 'matcher': side \(10\) and escalate_side"):
        matching.MatchSettings(side=10).checked("matcher")
    with pytest.raises(UdhError, match=r"^method 'unsupervised': match_side \(384\) and match_escalate_side \(4096"):
        matching.MatchSettings(escalate_side=4096).checked("unsupervised", "match_")
    with pytest.raises(UdhError, match=r"headings \(3\) must be one of 1, 2, 4"):
        matching.MatchSettings(headings=3).checked("matcher")
    near = matching.MatchSettings(side=256, refine_side=512).near_prior()
    assert (near.side, near.headings, near.refine_side, near.escalate_side) == (256, 1, 512, None)
